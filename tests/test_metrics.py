"""Tests of the metrics: PSNR/SSIM known values and gradients, masked variants, IoU, nearest
neighbours and surface distances on known shapes, and the LPIPS/CLIP models loaded from tiny
checkpoints in the official key layouts through the real loading path."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from humanvdm_core import metrics as M
from humanvdm_core.errors import MissingWeightsError
from humanvdm_core.perceptual import (
    ALEXNET_CONVS,
    LPIPS,
    LPIPS_CHANNELS,
    LPIPS_SCALE,
    LPIPS_SHIFT,
    CLIPImageEncoder,
    WeightsLayoutError,
)


def noise_image(h: int = 48, w: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


# ----------------------------------------------------------------------------- PSNR / SSIM

def test_psnr_known_values():
    a = noise_image()
    assert math.isinf(float(M.psnr(a, a)))
    base = np.full((32, 32, 3), 0.5, np.float32)
    assert float(M.psnr(base + 0.1, base)) == pytest.approx(20.0, abs=1e-4)  # MSE 0.01
    noisy = base + np.random.default_rng(1).normal(0.0, 0.05, base.shape).astype(np.float32)
    assert float(M.psnr(noisy, base)) == pytest.approx(-20 * np.log10(0.05), abs=0.15)  # 26.02 dB
    assert float(M.psnr(base * 255 + 10, base * 255, data_range=255.0)) == pytest.approx(20 * np.log10(25.5), abs=1e-3)
    batch = M.psnr(np.stack([base + 0.1, base + 0.01]), np.stack([base, base]))
    assert batch.shape == (2,) and batch[1].item() == pytest.approx(40.0, abs=1e-3)
    with pytest.raises(ValueError, match="differ in shape"):
        M.psnr(base, base[:-1])


def _ssim_reference(x: np.ndarray, y: np.ndarray, i: int, j: int) -> float:
    """SSIM of the 11x11 window whose top-left corner is (i, j), averaged over channels (direct sums)."""
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(x.shape[2]):
        a, b = x[i:i + 11, j:j + 11, c].astype(np.float64), y[i:i + 11, j:j + 11, c].astype(np.float64)
        ma, mb = (w * a).sum(), (w * b).sum()
        va, vb = (w * a * a).sum() - ma**2, (w * b * b).sum() - mb**2
        cov = (w * a * b).sum() - ma * mb
        vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_matches_definition():
    a = noise_image(seed=2)
    b = np.clip(a + np.random.default_rng(3).normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    assert float(M.ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    smap = M.ssim_map(a.astype(np.float64), b.astype(np.float64))
    assert smap.shape == (48 - 10, 40 - 10)
    for i, j in ((0, 0), (7, 13), (37, 29)):
        assert smap[i, j].item() == pytest.approx(_ssim_reference(a, b, i, j), abs=1e-9)
    # constant images: only the luminance term is left
    x, y = np.full((16, 16, 3), 0.5), np.full((16, 16, 3), 0.6)
    expected = (2 * 0.5 * 0.6 + 1e-4) / (0.25 + 0.36 + 1e-4)
    assert float(M.ssim(x, y)) == pytest.approx(expected, abs=1e-9)
    assert float(M.ssim(b, a)) == pytest.approx(float(M.ssim(a, b)), abs=1e-6)
    with pytest.raises(ValueError, match="smaller than"):
        M.ssim(a[:8], a[:8])


def test_ssim_and_psnr_have_gradients():
    target = torch.as_tensor(noise_image(seed=4))
    pred = (target + 0.1 * torch.randn_like(target, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    pred.requires_grad_(True)
    loss = (1.0 - M.ssim(pred, target)) - 0.01 * M.psnr(pred, target)
    loss.backward()
    assert pred.grad is not None and torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    # a gradient step improves SSIM
    with torch.no_grad():
        before = M.ssim(pred, target).item()
        after = M.ssim(pred - 0.5 * pred.grad / pred.grad.abs().max(), target).item()
    assert after > before


def test_masked_metrics():
    h = w = 40
    base = np.full((h, w, 3), 0.3, np.float32)
    base += 0.2 * noise_image(h, w, seed=5)
    alpha_gt = np.zeros((h, w), np.float32)
    alpha_gt[10:30, 10:20] = 1.0
    alpha_pred = np.zeros((h, w), np.float32)
    alpha_pred[10:30, 15:25] = 1.0
    union = M.union_mask(alpha_pred, alpha_gt)
    assert union.sum() == 20 * 15
    assert M.union_mask(alpha_pred[..., None], alpha_gt[..., None]).shape == (h, w)
    # error 0.1 inside the union only
    pred = base + 0.1 * union[..., None]
    assert float(M.masked_psnr(pred, base, alpha_pred, alpha_gt)) == pytest.approx(20.0, abs=1e-4)
    assert float(M.psnr(pred, base)) == pytest.approx(20.0 + 10 * np.log10(h * w / union.sum()), abs=1e-4)
    # error far (> 5 px) outside the union does not touch the masked scores
    far = base.copy()
    far[:, 35:] += 0.3
    assert math.isinf(float(M.masked_psnr(far, base, alpha_pred, alpha_gt)))
    assert float(M.masked_ssim(far, base, alpha_pred, alpha_gt)) == pytest.approx(1.0, abs=1e-6)
    assert float(M.ssim(far, base)) < 0.99
    # masked SSIM = mean of the map over the union's window centres
    smap = M.ssim_map(pred, base)
    assert float(M.ssim(pred, base, union)) == pytest.approx(float(smap[union[5:-5, 5:-5]].mean()), abs=1e-6)
    assert math.isnan(float(M.psnr(pred, base, np.zeros((h, w), bool))))


def test_silhouette_iou():
    a = np.zeros((30, 30))
    b = np.zeros((30, 30))
    assert M.silhouette_iou(a, b) == 1.0
    a[0:10, 0:10] = 1.0
    b[0:10, 5:15] = 0.9
    assert M.silhouette_iou(a, b) == pytest.approx(50 / 150)
    assert M.silhouette_iou(a, a * 0.4) == 0.0  # alpha 0.4 is outside


# ----------------------------------------------------------------------------- geometry

def sphere_points(n: int, radius: float, seed: int = 0) -> np.ndarray:
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * p / np.linalg.norm(p, axis=1, keepdims=True)


@pytest.mark.parametrize("brute_limit", [0, M.BRUTE_FORCE_PAIRS])
def test_nearest_neighbors_exact(monkeypatch, brute_limit):
    monkeypatch.setattr(M, "BRUTE_FORCE_PAIRS", brute_limit)  # 0: the grid search (with its retries)
    rng = np.random.default_rng(0)
    ref = np.concatenate([rng.normal(size=(3000, 3)), sphere_points(2000, 1.0)])
    query = np.concatenate([rng.normal(size=(1500, 3)), rng.normal(size=(20, 3)) * 50.0])  # and far outliers
    d, i = M.nearest_neighbors(query, ref)
    brute = np.linalg.norm(query[:, None] - ref[None], axis=2)
    np.testing.assert_allclose(d, brute.min(axis=1), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(query - ref[i], axis=1), d, atol=1e-12)


def test_closest_point_on_triangles():
    rng = np.random.default_rng(1)
    tri = rng.normal(size=(300, 3, 3))
    p = rng.normal(size=(300, 3)) * 2.0
    cp = M.closest_point_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    uv = rng.random((4000, 2))
    flip = uv.sum(axis=1) > 1
    uv[flip] = 1 - uv[flip]
    dense = tri[:, None, 0] + uv[None, :, :1] * (tri[:, None, 1] - tri[:, None, 0]) \
        + uv[None, :, 1:] * (tri[:, None, 2] - tri[:, None, 0])
    d_dense = np.linalg.norm(dense - p[:, None], axis=2).min(axis=1)
    d = np.linalg.norm(cp - p, axis=1)
    assert (d <= d_dense + 1e-12).all() and (d_dense - d).max() < 0.05
    # points straight above a big triangle: exactly their height
    a, b, c = np.array([[-5.0, 0, -5]]), np.array([[5.0, 0, -5]]), np.array([[0.0, 0, 5]])
    q = np.array([[0.1, 0.25, 0.2], [0.0, -0.5, 0.0]])
    dist = M.point_to_surface(q, np.concatenate([a, b, c]), np.array([[0, 1, 2]]), num_samples=200)
    np.testing.assert_allclose(dist, [0.25, 0.5], atol=1e-12)


def test_chamfer_of_two_spheres():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    outer = M.geometry_errors(sphere_points(10000, 0.9), sphere.vertices, sphere.faces, num_samples=20000)
    assert outer["p2s"] == pytest.approx(0.1, abs=0.003)
    assert outer["p2s_median"] == pytest.approx(0.1, abs=0.003)
    assert outer["s2p"] == pytest.approx(0.1, abs=0.01)
    assert outer["chamfer"] == pytest.approx(0.5 * (outer["p2s"] + outer["s2p"]))
    assert outer["height"] == pytest.approx(1.6, abs=1e-6)  # the mesh's vertical extent by default
    assert outer["chamfer_rel"] == pytest.approx(outer["chamfer"] / 1.6)
    inner = M.geometry_errors(sphere_points(2000, 0.5), sphere.vertices, sphere.faces, height=1.7, num_samples=20000)
    assert inner["p2s"] == pytest.approx(0.3, abs=0.003)
    assert inner["p2s_rel"] == pytest.approx(inner["p2s"] / 1.7)
    on = M.geometry_errors(sphere.vertices, sphere.vertices, sphere.faces, num_samples=20000)
    assert on["p2s"] < 1e-6 and on["s2p"] < 0.03  # s2p: to the nearest vertex (edges ~0.05)


def test_sample_surface_is_uniform_and_deterministic():
    # two unit squares of different area: samples split by area
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [5, 0, 0], [5, 3, 0], [2, 3, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    pts, fi = M.sample_surface(v, f, 20000, seed=3)
    assert abs(np.mean(fi >= 2) - 0.9) < 0.01
    pts2, _ = M.sample_surface(v, f, 20000, seed=3)
    np.testing.assert_array_equal(pts, pts2)
    with pytest.raises(ValueError, match="no surface"):
        M.sample_surface(v, np.zeros((0, 3), int), 10)


# ----------------------------------------------------------------------------- LPIPS

def alexnet_state(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for idx, cin, cout, k, _, _ in ALEXNET_CONVS:
        sd[f"features.{idx}.weight"] = torch.randn(cout, cin, k, k, generator=g) * (2.0 / (cin * k * k)) ** 0.5
        sd[f"features.{idx}.bias"] = 0.01 * torch.randn(cout, generator=g)
    sd["classifier.1.weight"] = torch.zeros(3, 3)  # torchvision's file has the classifier too
    return sd


def heads_state(seed: int = 1) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {f"lin{n}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for n, c in enumerate(LPIPS_CHANNELS)}


def test_lpips_loads_official_layout_and_scores(tmp_path):
    torch.save(alexnet_state(), tmp_path / "alexnet-owt-7be5be79.pth")
    from safetensors.torch import save_file

    save_file(heads_state(), str(tmp_path / "alex.safetensors"))
    model = LPIPS.from_files(tmp_path / "alexnet-owt-7be5be79.pth", tmp_path / "alex.safetensors")
    a = noise_image(64, 64, seed=6)
    b = np.clip(a + np.random.default_rng(7).normal(0, 0.05, a.shape), 0, 1).astype(np.float32)
    c = np.clip(a + np.random.default_rng(8).normal(0, 0.3, a.shape), 0, 1).astype(np.float32)
    assert float(model.distance(a, a)) == pytest.approx(0.0, abs=1e-7)
    d_small, d_big = float(model.distance(a, b)), float(model.distance(a, c))
    assert 0.0 < d_small < d_big
    assert float(model.distance(b, a)) == pytest.approx(d_small, rel=1e-5)
    assert model.distance(np.stack([a, a]), np.stack([b, c])).shape == (2,)

    # only the first head non-zero: LPIPS = spatial mean of the weighted, unit-normalised relu1 difference
    heads = {k: torch.zeros_like(v) for k, v in heads_state().items()}
    heads["lin0.model.1.weight"] = heads_state()["lin0.model.1.weight"]
    torch.save(heads, tmp_path / "alex.pth")
    m0 = LPIPS.from_files(tmp_path / "alexnet-owt-7be5be79.pth", tmp_path / "alex.pth")
    sd = alexnet_state()

    def relu1(img: np.ndarray) -> torch.Tensor:
        x = torch.as_tensor(img).permute(2, 0, 1)[None] * 2 - 1
        x = (x - torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1)) / torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1)
        f = F.relu(F.conv2d(x, sd["features.0.weight"], sd["features.0.bias"], stride=4, padding=2))
        return f / (f.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)

    expected = ((relu1(a) - relu1(b)) ** 2 * heads["lin0.model.1.weight"]).sum(dim=1).mean()
    assert float(m0.distance(a, b)) == pytest.approx(expected.item(), rel=1e-5)


def test_load_lpips_for_the_splat_loss(tmp_path):
    """metrics.load_lpips: AlexNet next to the heads file or in the same file; [-1, 1] inputs; gradients."""
    torch.save(alexnet_state(), tmp_path / "alexnet-owt-7be5be79.pth")
    torch.save(heads_state(), tmp_path / "alex.pth")
    torch.save({**alexnet_state(), **heads_state()}, tmp_path / "lpips_alex_combined.pth")
    a = torch.as_tensor(noise_image(64, 64, seed=12)).permute(2, 0, 1)[None]
    b = torch.as_tensor(noise_image(64, 64, seed=13)).permute(2, 0, 1)[None]
    reference = LPIPS.from_files(tmp_path / "alexnet-owt-7be5be79.pth", tmp_path / "alex.pth")
    expected = reference.distance(a[0].permute(1, 2, 0).numpy(), b[0].permute(1, 2, 0).numpy())
    for path in (tmp_path / "alex.pth", tmp_path / "lpips_alex_combined.pth"):
        net = M.load_lpips(path)
        x = a.clone().requires_grad_(True)
        d = net(x * 2 - 1, b * 2 - 1)
        assert d.shape == (1,) and d.item() == pytest.approx(float(expected), rel=1e-5)
        d.sum().backward()
        assert x.grad is not None and x.grad.abs().sum() > 0
    (tmp_path / "alone").mkdir()
    torch.save(heads_state(), tmp_path / "alone" / "alex.pth")
    with pytest.raises(MissingWeightsError, match="alexnet-owt-7be5be79.pth"):
        M.load_lpips(tmp_path / "alone" / "alex.pth")


def test_lpips_missing_and_wrong_files(tmp_path):
    torch.save(alexnet_state(), tmp_path / "alexnet.pth")
    with pytest.raises(MissingWeightsError, match="alex.pth"):
        LPIPS.from_files(tmp_path / "alexnet.pth", tmp_path / "nowhere" / "alex.pth")
    bad = heads_state()
    bad["lin5.model.1.weight"] = bad.pop("lin4.model.1.weight")
    torch.save(bad, tmp_path / "bad_heads.pth")
    with pytest.raises(WeightsLayoutError, match=r"missing keys: lin4\.model\.1\.weight; unexpected keys: lin5"):
        LPIPS.from_files(tmp_path / "alexnet.pth", tmp_path / "bad_heads.pth")
    feats = alexnet_state()
    feats["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    torch.save(feats, tmp_path / "bad_alexnet.pth")
    torch.save(heads_state(), tmp_path / "alex.pth")
    with pytest.raises(WeightsLayoutError, match=r"wrong shapes: features\.3\.weight"):
        LPIPS.from_files(tmp_path / "bad_alexnet.pth", tmp_path / "alex.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsLayoutError, match="cannot read"):
        LPIPS.from_files(tmp_path / "junk.pth", tmp_path / "alex.pth")


# ----------------------------------------------------------------------------- CLIP

WIDTH, LAYERS, PATCH, GRID, OUT = 32, 2, 8, 4, 16


def clip_state(seed: int = 0, text_tower: bool = True) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    sd = {k: 0.1 * torch.randn(*shape, generator=g)
          for k, shape in CLIPImageEncoder.official_keys(WIDTH, LAYERS, PATCH, GRID, OUT).items()}
    for k in list(sd):
        if k.endswith(("ln_1.weight", "ln_2.weight", "ln_pre.weight", "ln_post.weight")):
            sd[k] = 1.0 + sd[k]
    if text_tower:  # the full OpenAI checkpoint: ignored
        sd.update({"token_embedding.weight": torch.zeros(10, 8), "logit_scale": torch.tensor(4.6),
                   "transformer.resblocks.0.ln_1.weight": torch.ones(8)})
    return sd


def clip_reference(sd: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """The tower written with torch.nn.MultiheadAttention (an independent attention implementation)."""
    def ln(t, name):
        return F.layer_norm(t, (WIDTH,), sd[f"{name}.weight"], sd[f"{name}.bias"])

    t = F.conv2d(x, sd["visual.conv1.weight"], stride=PATCH).flatten(2).transpose(1, 2)
    t = torch.cat([sd["visual.class_embedding"].expand(len(t), 1, -1), t], 1) + sd["visual.positional_embedding"]
    t = ln(t, "visual.ln_pre")
    for n in range(LAYERS):
        b = f"visual.transformer.resblocks.{n}."
        mha = torch.nn.MultiheadAttention(WIDTH, 1, batch_first=True)
        mha.load_state_dict({"in_proj_weight": sd[b + "attn.in_proj_weight"], "in_proj_bias": sd[b + "attn.in_proj_bias"],
                             "out_proj.weight": sd[b + "attn.out_proj.weight"],
                             "out_proj.bias": sd[b + "attn.out_proj.bias"]})
        h = ln(t, b + "ln_1")
        t = t + mha(h, h, h, need_weights=False)[0]
        h = F.linear(ln(t, b + "ln_2"), sd[b + "mlp.c_fc.weight"], sd[b + "mlp.c_fc.bias"])
        t = t + F.linear(h * torch.sigmoid(1.702 * h), sd[b + "mlp.c_proj.weight"], sd[b + "mlp.c_proj.bias"])
    return ln(t[:, 0], "visual.ln_post") @ sd["visual.proj"]


def test_clip_loads_official_layout(tmp_path):
    sd = clip_state()
    torch.save(sd, tmp_path / "ViT-tiny.pt")
    model = CLIPImageEncoder.from_file(tmp_path / "ViT-tiny.pt")
    assert model.input_resolution == PATCH * GRID
    a, b = noise_image(50, 70, seed=9), noise_image(50, 70, seed=10)
    x = model.preprocess(np.stack([a, b]))
    assert x.shape == (2, 3, 32, 32)
    with torch.no_grad():
        np.testing.assert_allclose(model(x).numpy(), clip_reference(sd, x).numpy(), atol=1e-5)
    assert float(model.similarity(a, a)) == pytest.approx(1.0, abs=1e-5)
    assert float(model.similarity(a, b)) < 1.0 - 1e-4
    # safetensors, and a tower-only state dict without the "visual." prefix
    from safetensors.torch import save_file

    tower = {k[len("visual."):]: v for k, v in sd.items() if k.startswith("visual.")}
    save_file(tower, str(tmp_path / "tower.safetensors"))
    again = CLIPImageEncoder.from_file(tmp_path / "tower.safetensors")
    np.testing.assert_allclose(again.embed(a).numpy(), model.embed(a).numpy(), atol=1e-6)


def test_clip_preprocess_centre_crop():
    model = CLIPImageEncoder(WIDTH, 0, PATCH, GRID, OUT)
    img = np.zeros((64, 128, 3), np.float32)
    img[:, 32:96] = 1.0  # the centre square is white, the sides black
    x = model.preprocess(img) * model.std + model.mean
    assert x.shape == (1, 3, 32, 32)
    assert float(x[..., 1:-1].min()) > 0.99 and float(x[..., 0].max()) < 0.97  # edge columns: bicubic blend


def test_clip_missing_and_wrong_files(tmp_path):
    with pytest.raises(MissingWeightsError, match="ViT-B-32.pt"):
        CLIPImageEncoder.from_file(tmp_path / "ViT-B-32.pt")
    sd = clip_state()
    del sd["visual.transformer.resblocks.1.mlp.c_fc.bias"]
    sd["visual.transformer.resblocks.1.mlp.fc1.bias"] = torch.zeros(4 * WIDTH)
    torch.save(sd, tmp_path / "renamed.pt")
    with pytest.raises(WeightsLayoutError, match=r"missing keys: visual\.transformer\.resblocks\.1\.mlp\.c_fc\.bias; "
                                                 r"unexpected keys: visual\.transformer\.resblocks\.1\.mlp\.fc1\.bias"):
        CLIPImageEncoder.from_file(tmp_path / "renamed.pt")
    torch.save(heads_state(), tmp_path / "lpips_heads.pth")
    with pytest.raises(WeightsLayoutError, match=r"missing keys: .*visual\.conv1\.weight"):
        CLIPImageEncoder.from_file(tmp_path / "lpips_heads.pth")


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.script / save: writing the test file
def test_clip_loads_torchscript_archive(tmp_path):
    """OpenAI ships ViT-B-32.pt as a TorchScript archive: its module's state dict is read."""
    sd = clip_state()

    class Holder(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x

    root = Holder()
    for key, value in sd.items():
        *path, leaf = key.split(".")
        mod = root
        for part in path:
            if not hasattr(mod, part):
                mod.add_module(part, Holder())
            mod = getattr(mod, part)
        mod.register_parameter(leaf, torch.nn.Parameter(value.clone().half()))  # OpenAI stores fp16
    try:
        torch.jit.save(torch.jit.script(root), str(tmp_path / "ViT-B-32.pt"))
    except Exception as e:  # TorchScript unavailable in this torch build
        pytest.skip(f"cannot write a TorchScript archive here: {e}")
    model = CLIPImageEncoder.from_file(tmp_path / "ViT-B-32.pt")
    ref = CLIPImageEncoder.from_file(_saved(tmp_path, {k: v.half().float() for k, v in sd.items()}))
    a = noise_image(40, 40, seed=11)
    np.testing.assert_allclose(model.embed(a).numpy(), ref.embed(a).numpy(), atol=1e-6)


def _saved(tmp_path, sd: dict[str, torch.Tensor]):
    path = tmp_path / "plain.pt"
    torch.save(sd, path)
    return path
