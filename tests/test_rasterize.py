"""Tests for the Gaussian rasterizer: tiled torch path vs dense reference, the numba kernels vs the torch path
(their oracle), gradients, conventions, gsplat."""

from __future__ import annotations

import math
import sys
import types

import pytest
import torch

from humanvdm_core.splat import rasterize as rz
from humanvdm_core.splat import rasterize_gaussians


def _scene(n: int, seed: int = 0, dtype: torch.dtype = torch.float64, dim: int = 3, cams: int = 2) -> dict:
    g = torch.Generator().manual_seed(seed)
    viewmats = torch.eye(4, dtype=dtype).repeat(cams, 1, 1)
    for c in range(cams):  # cameras on a small arc around the origin, 3 units away, looking at it
        ang = 0.4 * c
        rot = torch.tensor([[math.cos(ang), 0.0, -math.sin(ang)], [0.0, 1.0, 0.0],
                            [math.sin(ang), 0.0, math.cos(ang)]], dtype=dtype)
        viewmats[c, :3, :3] = rot
        viewmats[c, :3, 3] = torch.tensor([0.05 * c, -0.03, 3.0], dtype=dtype)
    Ks = torch.tensor([[55.0, 0.0, 31.0], [0.0, 52.0, 22.5], [0.0, 0.0, 1.0]], dtype=dtype).repeat(cams, 1, 1)
    return dict(
        means=torch.randn(n, 3, generator=g, dtype=dtype) * 0.6,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.02,
        opacities=torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05,
        colors=torch.rand(n, dim, generator=g, dtype=dtype),
        viewmats=viewmats, Ks=Ks,
    )


def _camera(dtype: torch.dtype = torch.float64, f: float = 100.0, w: int = 64, h: int = 48) -> tuple:
    viewmats = torch.eye(4, dtype=dtype)[None]
    Ks = torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]], dtype=dtype)[None]
    return viewmats, Ks


def _one(mean, scale, opacity=0.8, color=(1.0, 0.0, 0.0), dtype=torch.float64) -> dict:
    return dict(means=torch.tensor([mean], dtype=dtype), quats=torch.tensor([[1.0, 0, 0, 0]], dtype=dtype),
                scales=torch.full((1, 3), scale, dtype=dtype), opacities=torch.tensor([opacity], dtype=dtype),
                colors=torch.tensor([color], dtype=dtype))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-5)])
@pytest.mark.parametrize("size,tile", [((64, 48), 16), ((70, 37), 16), ((45, 33), 8), ((50, 41), 4)])
def test_tiled_matches_dense(dtype, tol, size, tile, monkeypatch):
    monkeypatch.setattr(rz, "TORCH_TILE_SIZE", tile)
    s = _scene(80, seed=1, dtype=dtype)
    bg = torch.tensor([[0.2, 0.3, 0.4], [1.0, 0.0, 0.5]], dtype=dtype)
    w, h = size
    fast = rasterize_gaussians(**s, width=w, height=h, backgrounds=bg, backend="torch")
    assert fast[2]["tile_size"] == tile
    ref = rasterize_gaussians(**s, width=w, height=h, backgrounds=bg, backend="dense")
    assert fast[0].shape == (2, h, w, 3) and fast[1].shape == (2, h, w, 1)
    assert (fast[0] - ref[0]).abs().max() < tol
    assert (fast[1] - ref[1]).abs().max() < tol
    assert fast[1].max() > 0.9  # the scene actually covers pixels, some nearly opaque
    assert fast[2]["radii"].shape == (2, 80, 2) and fast[2]["means2d"].shape == (2, 80, 2)


def test_tiled_matches_dense_features_and_per_camera_colors():
    s = _scene(40, seed=2, dim=5)
    s["colors"] = torch.rand(2, 40, 5, dtype=torch.float64)
    fast = rasterize_gaussians(**s, width=40, height=40, backend="torch")
    ref = rasterize_gaussians(**s, width=40, height=40, backend="dense")
    assert fast[0].shape == (2, 40, 40, 5)
    assert torch.allclose(fast[0], ref[0], atol=1e-10) and torch.allclose(fast[1], ref[1], atol=1e-10)


@pytest.mark.parametrize("clumped", [False, True])
def test_tiled_gradients_match_dense(clumped, monkeypatch):
    s = _scene(30, seed=3)
    if clumped:  # opaque and overlapping: pixels and whole tiles terminate early, over several chunks
        s = _scene(300, seed=3)
        s["means"] = s["means"] * 0.2
        s["scales"] = s["scales"] * 2
        s["opacities"] = s["opacities"].clamp(min=0.9)
        monkeypatch.setattr(rz, "CHUNK_ELEMENTS", 8 * 8 * 64)  # batches of 8 tiles, 8 Gaussians per step
        monkeypatch.setattr(rz, "CHUNK_GAUSSIANS", 8)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.3, 0.2, 0.1]], dtype=torch.float64, requires_grad=True)
    weights = torch.rand(2, 48, 64, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    grads = {}
    for backend in ("torch", "dense"):
        leaves = {k: v.clone().requires_grad_(True) for k, v in s.items()}
        colors, alphas, _ = rasterize_gaussians(**leaves, width=64, height=48, backgrounds=bg, backend=backend)
        loss = (torch.cat([colors, alphas], -1) * weights).sum()
        grads[backend] = torch.autograd.grad(loss, list(leaves.values()) + [bg])
    for a, b in zip(grads["torch"], grads["dense"], strict=True):
        assert torch.allclose(a, b, atol=1e-9, rtol=1e-7)
    assert grads["torch"][0].abs().max() > 1e-3


@pytest.mark.parametrize("backend", ["torch", "numba"])
@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmats"])
def test_gradients_match_finite_differences(name, backend):
    if backend == "numba":
        pytest.importorskip("numba")
    s = _scene(5, seed=4, cams=1)
    s["opacities"] = s["opacities"].clamp(max=0.8)
    weights = torch.rand(1, 20, 24, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    s["Ks"] = torch.tensor([[[20.0, 0.0, 12.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)

    def loss(value: torch.Tensor) -> torch.Tensor:
        colors, alphas, _ = rasterize_gaussians(**dict(s, **{name: value}), width=24, height=20,
                                                backend=backend)
        return (torch.cat([colors, alphas], -1) * weights).sum()

    x = s[name].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(x), [x])
    eps = 1e-6
    flat = x.detach().flatten()
    numeric = torch.zeros_like(flat)
    entries = range(flat.numel()) if name != "viewmats" else [i for i in range(12)]  # not the [0 0 0 1] row
    for i in entries:
        plus, minus = flat.clone(), flat.clone()
        plus[i] += eps
        minus[i] -= eps
        with torch.no_grad():
            numeric[i] = (loss(plus.view_as(x)) - loss(minus.view_as(x))) / (2 * eps)
    analytic = grad.flatten()[list(entries)]
    numeric = numeric[list(entries)]
    assert analytic.abs().max() > 1e-3  # the parameter really influences the image
    assert torch.allclose(analytic, numeric, atol=1e-5, rtol=1e-4), (analytic, numeric)


def test_single_gaussian_projects_to_K_RX_t_with_expected_spread():
    dtype = torch.float64
    ang = 0.3
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, :3] = torch.tensor([[math.cos(ang), 0.0, math.sin(ang)], [0.0, 1.0, 0.0],
                                    [-math.sin(ang), 0.0, math.cos(ang)]], dtype=dtype)
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 2.5], dtype=dtype)
    f, w, h = 150.0, 96, 80
    K = torch.tensor([[f, 0.0, 47.3], [0.0, f * 1.02, 41.1], [0.0, 0.0, 1.0]], dtype=dtype)
    X = torch.tensor([0.05, 0.12, -0.04], dtype=dtype)
    cam = viewmat[:3, :3] @ X + viewmat[:3, 3]
    uvw = K @ cam
    u, v = (uvw[:2] / uvw[2]).tolist()
    scale = 0.03
    g = _one(X.tolist(), scale, opacity=0.5)
    colors, alphas, meta = rasterize_gaussians(**g, viewmats=viewmat[None], Ks=K[None], width=w, height=h,
                                               eps2d=0.0, backend="torch")
    assert torch.allclose(meta["means2d"][0, 0], torch.tensor([u, v], dtype=dtype))
    a = alphas[0, :, :, 0]
    iy, ix = divmod(int(a.argmax()), w)
    assert abs(ix + 0.5 - u) <= 0.5 and abs(iy + 0.5 - v) <= 0.5
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dtype) + 0.5, torch.arange(w, dtype=dtype) + 0.5, indexing="ij")
    cx, cy = float((a * xs).sum() / a.sum()), float((a * ys).sum() / a.sum())
    assert abs(cx - u) < 0.05 and abs(cy - v) < 0.05
    # Spread: alpha(d) = o exp(-d^2 / (2 sigma^2)) along x through the peak row, sigma ~ f s / z.
    sigma_expected = f * scale / float(cam[2])
    sx = float(meta["conics"][0, 0, 0]) ** -0.5
    assert abs(sx - sigma_expected) / sigma_expected < 0.06  # off-axis: the EWA Jacobian stretches a little
    z = float(cam[2])
    fit = ((xs - u) ** 2 + (ys - v) ** 2)[a > 0.05]
    logs = torch.log(a[a > 0.05] / 0.5)
    sigma_fit = float(torch.sqrt(-(fit * fit).sum() / (2 * (fit * logs).sum())))
    assert abs(sigma_fit - f * scale / z) / (f * scale / z) < 0.06
    assert colors[0, iy, ix, 1:].abs().max() == 0 and colors[0, iy, ix, 0] > 0.45


def test_on_axis_spread_is_exact_and_includes_eps2d():
    viewmats, Ks = _camera(f=120.0, w=64, h=64)
    Ks[0, 0, 2] = Ks[0, 1, 2] = 32.5  # the Gaussian lands on the centre of pixel (32, 32)
    for eps2d in (0.0, 0.3):
        g = _one([0.0, 0.0, 3.0], 0.1, opacity=0.6)
        _, alphas, _ = rasterize_gaussians(**g, viewmats=viewmats, Ks=Ks, width=64, height=64, eps2d=eps2d,
                                           backend="torch")
        a = alphas[0, 32, :, 0]
        assert abs(float(a[32]) - 0.6) < 1e-12
        sigma2 = (120.0 * 0.1 / 3.0) ** 2 + eps2d
        for d in (1, 3, 5):
            assert abs(float(a[32 + d]) - 0.6 * math.exp(-0.5 * d * d / sigma2)) < 1e-12


def test_depth_ordering_near_opaque_hides_far():
    viewmats, Ks = _camera()
    near = _one([0.0, 0.0, 2.0], 0.1, opacity=1.0, color=(1.0, 0.0, 0.0))
    far = _one([0.0, 0.0, 4.0], 0.2, opacity=1.0, color=(0.0, 1.0, 0.0))
    both = {k: torch.cat([far[k], near[k]]) for k in near}  # far first in memory: order must come from depth
    for backend in ("torch", "dense"):
        colors, alphas, _ = rasterize_gaussians(**both, viewmats=viewmats, Ks=Ks, width=64, height=48,
                                                backend=backend)
        centre = colors[0, 24, 32]
        assert centre[0] > 0.99 and centre[1] < 0.01
        assert alphas[0, 24, 32, 0] > 0.98
    flipped = {k: torch.cat([near[k], far[k]]) for k in near}
    assert torch.allclose(rasterize_gaussians(**flipped, viewmats=viewmats, Ks=Ks, width=64, height=48)[0],
                          rasterize_gaussians(**both, viewmats=viewmats, Ks=Ks, width=64, height=48)[0])


def test_background_compositing():
    viewmats, Ks = _camera()
    g = _one([0.0, 0.0, 3.0], 0.1, opacity=0.7, color=(0.2, 0.4, 0.6))
    bg = torch.tensor([[1.0, 0.5, 0.0]], dtype=torch.float64)
    colors, alphas, _ = rasterize_gaussians(**g, viewmats=viewmats, Ks=Ks, width=64, height=48, backgrounds=bg)
    expected = alphas * torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64) + (1 - alphas) * bg[0]
    assert torch.allclose(colors, expected, atol=1e-12)
    assert torch.allclose(colors[0, 0, 0], bg[0])  # a far corner is pure background
    empty = {k: v[:0] for k, v in g.items()}
    colors, alphas, _ = rasterize_gaussians(**empty, viewmats=viewmats, Ks=Ks, width=20, height=10, backgrounds=bg)
    assert torch.equal(colors, bg[0].expand(1, 10, 20, 3)) and torch.equal(alphas, torch.zeros(1, 10, 20, 1,
                                                                                                dtype=torch.float64))


@pytest.mark.parametrize("z", [-3.0, 0.005, 2e3])
def test_culling_behind_near_and_far(z):
    viewmats, Ks = _camera()
    g = _one([0.0, 0.0, z], 0.1, opacity=0.9)
    for backend in ("torch", "dense"):
        colors, alphas, meta = rasterize_gaussians(**g, viewmats=viewmats, Ks=Ks, width=64, height=48,
                                                   near_plane=0.01, far_plane=1e3, backend=backend)
        assert alphas.abs().max() == 0 and colors.abs().max() == 0
        assert int(meta["radii"].abs().max()) == 0


def test_camera_looking_away_and_offscreen_culled():
    viewmats, Ks = _camera()
    g = _one([0.0, 0.0, 3.0], 0.1)
    away = viewmats.clone()
    away[0, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))  # turned around
    _, alphas, meta = rasterize_gaussians(**g, viewmats=away, Ks=Ks, width=64, height=48)
    assert alphas.max() == 0 and int(meta["radii"].max()) == 0
    side = _one([5.0, 0.0, 3.0], 0.1)  # far outside the field of view
    _, alphas, meta = rasterize_gaussians(**side, viewmats=viewmats, Ks=Ks, width=64, height=48)
    assert alphas.max() == 0 and int(meta["radii"].max()) == 0


def test_memory_bounded_path_many_batches_and_early_termination(monkeypatch):
    torch.manual_seed(0)
    n = 3000
    s = _scene(n, seed=5, dtype=torch.float32, cams=1)
    s["means"] = s["means"] * 0.3  # a dense clump: long per-tile lists, opaque enough to terminate early
    s["opacities"] = s["opacities"].clamp(min=0.5)
    full = rasterize_gaussians(**s, width=64, height=48, backend="torch")
    monkeypatch.setattr(rz, "TORCH_TILE_SIZE", 16)
    full16 = rasterize_gaussians(**s, width=64, height=48, backend="torch")
    assert torch.allclose(full16[0], full[0], atol=1e-6)
    monkeypatch.setattr(rz, "CHUNK_ELEMENTS", 4096)  # -> batches of one tile x 16 Gaussians
    monkeypatch.setattr(rz, "CHUNK_GAUSSIANS", 16)
    leaves = {k: v.clone().requires_grad_(True) for k, v in s.items()}
    saved: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:  # distinct storages saved for backward, in bytes
        saved[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        small = rasterize_gaussians(**leaves, width=64, height=48, backend="torch")
    assert torch.allclose(small[0], full[0], atol=1e-6) and torch.allclose(small[1], full[1], atol=1e-6)
    n_isect = small[2]["n_intersections"][0]
    assert n_isect > 20 * 12  # many Gaussians per tile
    # Saved activations scale with Gaussians + pixels, not with intersections x tile pixels (one float
    # tensor of that size alone would be ~10 MB here).
    assert sum(saved.values()) < 4 * (n * 200 + 64 * 48 * 64) < 4 * n_isect * 256 / 3, sum(saved.values())
    small[0].sum().backward()
    assert all(torch.isfinite(v.grad).all() for v in leaves.values())
    ref = rasterize_gaussians(**{k: v.double() for k, v in s.items()}, width=64, height=48, backend="dense")
    assert torch.allclose(small[0].double(), ref[0], atol=1e-4)


def test_meta_means2d_gradient_for_densification():
    s = _scene(20, seed=6)
    s["means"].requires_grad_(True)
    colors, _, meta = rasterize_gaussians(**s, width=64, height=48)
    meta["means2d"].retain_grad()
    colors.sum().backward()
    assert meta["means2d"].grad.shape == (2, 20, 2) and meta["means2d"].grad.abs().max() > 0


def test_bad_inputs_and_backends():
    s = _scene(4, seed=7)
    with pytest.raises(ValueError, match="means"):
        rasterize_gaussians(**dict(s, means=s["means"][:, :2]), width=8, height=8)
    with pytest.raises(ValueError, match="backend"):
        rasterize_gaussians(**s, width=8, height=8, backend="opengl")
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            rasterize_gaussians(**s, width=8, height=8, backend="gsplat")
        expected = "numba" if rz._numba_available() else "torch"
        assert rasterize_gaussians(**s, width=8, height=8, backend="auto")[2]["backend"] == expected


def test_a_gpu_without_gsplat_is_warned(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setitem(sys.modules, "gsplat", None)  # `import gsplat` raises ImportError
    warning = rz.gsplat_missing_warning()
    assert warning is not None and "gsplat does not import" in warning and "28x slower" in warning
    monkeypatch.setitem(sys.modules, "gsplat", types.ModuleType("gsplat"))  # gsplat imports: nothing to say
    assert rz.gsplat_missing_warning() is None
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # no GPU: the CPU paths are the right ones
    monkeypatch.setitem(sys.modules, "gsplat", None)
    assert rz.gsplat_missing_warning() is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat needs CUDA")
def test_gsplat_matches_torch_backend():
    pytest.importorskip("gsplat")
    s = _scene(300, seed=8, dtype=torch.float32)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0]])
    ours = rasterize_gaussians(**s, width=64, height=48, backgrounds=bg, backend="torch")
    cuda = {k: v.cuda() for k, v in s.items()}
    theirs = rasterize_gaussians(**cuda, width=64, height=48, backgrounds=bg.cuda(), backend="gsplat")
    assert theirs[0].shape == ours[0].shape and theirs[1].shape == ours[1].shape
    # Same conventions; float32 CUDA vs CPU arithmetic, and gsplat releases before the opacity-tightened
    # screen boxes cut a few faint (alpha < 0.011) pixels at tile borders: small max, tiny mean difference.
    for a, b in ((theirs[0].cpu(), ours[0]), (theirs[1].cpu(), ours[1])):
        assert (a - b).abs().max() < 2e-2 and (a - b).abs().mean() < 1e-3


# ----------------------------------------------------------------------------------------- numba kernels


def _hard_scene(n: int, seed: int, dtype: torch.dtype = torch.float64) -> dict:
    """Anisotropic, overlapping Gaussians; a clump opaque enough that pixels and whole tiles terminate
    early; some culled (behind the camera, beyond the far plane, off screen, too transparent)."""
    s = _scene(n, seed=seed, dtype=dtype)
    s["means"][: n // 2] *= 0.25  # the clump
    s["scales"][: n // 2] *= 1.5
    s["opacities"][: n // 2] = s["opacities"][: n // 2].clamp(min=0.85)
    s["opacities"][0] = 1.0  # alpha clamped at ALPHA_MAX somewhere
    s["means"][-1] = torch.tensor([0.0, 0.0, -6.0], dtype=dtype)  # behind both cameras
    s["means"][-2] = torch.tensor([30.0, 0.0, 1.0], dtype=dtype)  # far off screen
    s["means"][-3] = torch.tensor([0.0, 0.0, 5e3], dtype=dtype)  # beyond far_plane=1e3
    s["opacities"][-4] = 1e-3  # below 1/255
    return s


def _render_with_grads(s: dict, bg: torch.Tensor, weights: torch.Tensor, backend: str, width: int,
                       height: int) -> tuple[torch.Tensor, torch.Tensor, dict, tuple[torch.Tensor, ...]]:
    leaves = {k: v.clone().requires_grad_(True) for k, v in s.items()}
    bg = bg.clone().requires_grad_(True)
    colors, alphas, meta = rasterize_gaussians(**leaves, width=width, height=height, backgrounds=bg,
                                               far_plane=1e3, backend=backend)
    loss = (torch.cat([colors, alphas], -1) * weights).sum()
    grads = torch.autograd.grad(loss, list(leaves.values()) + [bg])
    return colors.detach(), alphas.detach(), meta, grads


@pytest.mark.parametrize("size", [(64, 48), (70, 37)])
def test_numba_matches_torch_images_and_gradients(size):
    pytest.importorskip("numba")
    w, h = size
    s = _hard_scene(400, seed=11)
    bg = torch.tensor([[0.2, 0.3, 0.4], [1.0, 0.0, 0.5]], dtype=torch.float64)
    weights = torch.rand(2, h, w, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    fast = _render_with_grads(s, bg, weights, "numba", w, h)
    ref = _render_with_grads(s, bg, weights, "torch", w, h)
    assert fast[2]["backend"] == "numba" and fast[2]["tile_size"] == rz.NUMBA_TILE_SIZE
    assert fast[0].shape == (2, h, w, 3) and fast[1].shape == (2, h, w, 1)
    assert (fast[0] - ref[0]).abs().max() < 1e-12 and (fast[1] - ref[1]).abs().max() < 1e-12
    assert ref[1].max() > 0.999  # some pixels stopped at T <= 1e-4 ...
    assert (ref[1] < 0.5).any()  # ... and some are mostly background
    radii = fast[2]["radii"]
    assert int((radii[:, -3:] > 0).sum()) == 0 and int((radii[:, -4] > 0).sum()) == 0  # culled
    for name, a, b in zip(list(s) + ["backgrounds"], fast[3], ref[3], strict=True):
        assert torch.allclose(a, b, rtol=1e-7, atol=1e-9), name
    assert fast[3][0].abs().max() > 1e-3


def test_numba_matches_torch_float32_features_per_camera_colors():
    pytest.importorskip("numba")
    s = _hard_scene(300, seed=12, dtype=torch.float32)
    s["colors"] = torch.rand(2, 300, 5, generator=torch.Generator().manual_seed(3))
    bg = torch.rand(2, 5, generator=torch.Generator().manual_seed(4))
    weights = torch.rand(2, 41, 50, 6, generator=torch.Generator().manual_seed(5))
    fast = _render_with_grads(s, bg, weights, "numba", 50, 41)
    ref = _render_with_grads(s, bg, weights, "torch", 50, 41)
    assert fast[0].dtype == torch.float32 and fast[1].dtype == torch.float32
    assert (fast[0] - ref[0]).abs().max() < 1e-5 and (fast[1] - ref[1]).abs().max() < 1e-5
    # float64 kernels against float32 torch arithmetic: agreement to float32 precision, relative to each
    # gradient's scale
    for name, a, b in zip(list(s) + ["backgrounds"], fast[3], ref[3], strict=True):
        assert a.dtype == torch.float32, name
        assert (a - b).abs().max() <= 1e-4 * b.abs().max() + 1e-6, name


def test_numba_matches_dense_reference():
    pytest.importorskip("numba")
    s = _hard_scene(120, seed=13)
    bg = torch.tensor([[0.5, 0.1, 0.9], [0.0, 0.0, 0.0]], dtype=torch.float64)
    fast = rasterize_gaussians(**s, width=45, height=33, backgrounds=bg, far_plane=1e3, backend="numba")
    ref = rasterize_gaussians(**s, width=45, height=33, backgrounds=bg, far_plane=1e3, backend="dense")
    assert (fast[0] - ref[0]).abs().max() < 1e-10 and (fast[1] - ref[1]).abs().max() < 1e-10


def test_numba_composite_gradcheck():
    """torch.autograd.gradcheck of the compiled compositing alone, float64, away from every threshold."""
    rn = pytest.importorskip("humanvdm_core.splat.rasterize_numba")
    g = torch.Generator().manual_seed(6)
    n, w, h = 6, 13, 11
    means2d = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([w, h]) * 0.6 + 2.0
    # Broad Gaussians (variances 40-60 px^2) with opacities 0.2-0.6: every alpha in the image stays above
    # 1/255 and below the clamp, and T never nears 1e-4, so finite differences cross no cut-off.
    cov = torch.rand(n, 3, generator=g, dtype=torch.float64)
    a, b, c = 40 + 20 * cov[:, 0], 10 * (cov[:, 1] - 0.5), 40 + 20 * cov[:, 2]
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], -1)
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.4 + 0.2
    colors = torch.rand(n, 4, generator=g, dtype=torch.float64)
    depths = torch.rand(n, generator=g, dtype=torch.float64)
    radii = torch.full((n, 2), 20, dtype=torch.int32)  # every Gaussian covers the whole image
    bins = rn.bin_gaussians(means2d, radii, depths, 4, w, h)
    assert bins.gids.size == n * math.ceil(w / 4) * math.ceil(h / 4)
    inputs = tuple(t.clone().requires_grad_(True) for t in (means2d, conics, opacities, colors))
    assert torch.autograd.gradcheck(lambda *x: rn.composite(*x, bins), inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_binning_matches_torch_intersections(dtype):
    rn = pytest.importorskip("humanvdm_core.splat.rasterize_numba")
    s = _hard_scene(500, seed=15, dtype=dtype)
    s["means"][100:140] = s["means"][60:100]  # equal depths: ties keep index order in both
    proj = rz.project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], s["viewmats"], s["Ks"],
                                70, 37, far_plane=1e3)
    for cam in range(2):
        m2, radii, depths = proj["means2d"][cam], proj["radii"][cam], proj["depths"][cam]
        for tile in (4, 16):
            tiles_w, tiles_h = math.ceil(70 / tile), math.ceil(37 / tile)
            gids, tile_ids = rz._intersect_tiles(m2, radii, depths, tile, tiles_w, tiles_h)
            bins = rn.bin_gaussians(m2, radii, depths, tile, 70, 37)
            assert gids.numel() > 500 and torch.equal(torch.from_numpy(bins.gids), gids)
            counts = torch.bincount(tile_ids, minlength=tiles_w * tiles_h)
            assert torch.equal(torch.from_numpy(bins.starts).diff(), counts)
            assert bins.order.tolist() == torch.nonzero(counts).flatten().tolist()  # busy tiles, row-major


def test_numba_threads_follow_torch_and_results_are_deterministic():
    rn = pytest.importorskip("humanvdm_core.splat.rasterize_numba")
    import numba

    s = _hard_scene(300, seed=14)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.3, 0.2, 0.1]], dtype=torch.float64)
    weights = torch.rand(2, 48, 64, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            with rn._Threads():
                assert numba.get_num_threads() == min(threads, numba.config.NUMBA_NUM_THREADS)
            results.append(_render_with_grads(s, bg, weights, "numba", 64, 48))
    finally:
        torch.set_num_threads(before)
    one, two = results
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])
    assert all(torch.equal(a, b) for a, b in zip(one[3], two[3], strict=True))


def test_numba_empty_and_all_culled():
    pytest.importorskip("numba")
    viewmats, Ks = _camera()
    bg = torch.tensor([[1.0, 0.5, 0.0]], dtype=torch.float64)
    g = _one([0.0, 0.0, -3.0], 0.1)  # behind the camera
    for scene in (g, {k: v[:0] for k, v in g.items()}):
        leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
        colors, alphas, meta = rasterize_gaussians(**leaves, viewmats=viewmats, Ks=Ks, width=20, height=10,
                                                   backgrounds=bg, backend="numba")
        assert torch.equal(colors.detach(), bg[0].expand(1, 10, 20, 3)) and alphas.abs().max() == 0
        assert meta["n_intersections"] == [0]
        colors.sum().backward()
        assert all(v.grad is None or not v.grad.any() for v in leaves.values())
