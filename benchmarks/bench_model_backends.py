"""Speed of the real-model backends on this machine's CPU, per frame at 576² input.

What it measures (random weights: speed does not depend on the values; the architectures are the
official ones, so "real size" is what ``RealESRGAN_x4plus.pth`` / ``codeformer.pth`` / RIFE v4.6
``flownet.pkl`` would cost):

- ``realesrgan``: one 576² RGBA frame -> 1080² (RRDBNet ×4 tiled 384 + area resize).  The tiny
  model (num_feat 8, 1 block) is timed on the whole frame.  The real-size RRDBNet (64 features, 23
  blocks, 16.7 M parameters) takes minutes per 576² frame on a small CPU, so by default it is timed
  on a ``--probe``² input and extrapolated to 576² by pixel count times the tiling overhead (the
  tiles' context pixels); ``--full`` times the whole frame instead.
- ``codeformer``: detection on the frame + one 512² face through CodeFormer (94 M parameters for
  the real size) + paste-back; the per-frame estimate adds the Real-ESRGAN background above.
- ``rife``: one in-between frame from a 576² RGBA pair (RIFE v4.6 IFNet, 5.3 M parameters), tiny
  and real size.
- ``pervfi``: one in-between frame (t = 0.5) from a 576² RGBA pair: RAFT flows both ways (12
  iterations, 5.3 M parameters) + the PerVFI v00 generator (8.7 M parameters, normalizing-flow
  decoder, pure-PyTorch softsplat and deformable convolution), tiny and real size (the real one is
  timed once, after a warm-up on a small crop).
- the embedded backends on the same frames, for comparison.

Run:  .venv/bin/python benchmarks/bench_model_backends.py [--threads 2] [--probe 96] [--full]
Writes benchmarks/results/model_backends.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import save_result  # noqa: E402

SIZE, TARGET, TILE, TILE_PAD = 576, 1080, 384, 24
PHOTO = REPO.parent / "shared" / "fixtures" / "photos" / "pifu_ryota.png"


def timed(fn, repeat: int = 1) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def test_frame(seed: int = 0) -> np.ndarray:
    """A 576² RGBA frame: the fixture photo when present (it has a face), else smooth noise."""
    import cv2

    if PHOTO.is_file():
        bgra = cv2.imread(str(PHOTO), cv2.IMREAD_UNCHANGED)
        bgra = cv2.resize(bgra, (SIZE, SIZE), interpolation=cv2.INTER_CUBIC)
        rgb = cv2.cvtColor(bgra[..., :3], cv2.COLOR_BGR2RGB).astype(np.float32) / 255
        alpha = bgra[..., 3:].astype(np.float32) / 255 if bgra.shape[2] == 4 else np.ones((SIZE, SIZE, 1), np.float32)
        return np.concatenate([rgb, alpha], -1)
    rng = np.random.default_rng(seed)
    rgb = cv2.GaussianBlur(rng.random((SIZE, SIZE, 3)).astype(np.float32), (0, 0), 3.0)
    return np.concatenate([rgb, np.ones((SIZE, SIZE, 1), np.float32)], -1)


def tile_overhead(size: int, tile: int, pad: int) -> float:
    """Pixels the tiled RRDBNet processes (tiles plus context) / pixels of the frame."""
    starts = range(0, size, tile)
    side = sum(min(s + tile, size) - s + 2 * pad for s in starts)
    return side * side / (size * size)


def save_models(folder: Path) -> tuple[dict[str, Path], dict[str, float]]:
    """Random-weight models saved in their official layouts; (paths, millions of parameters)."""
    import torch

    from humanvdm_core.interpolate import pervfi, raft
    from humanvdm_core.interpolate.rife import IFNet
    from humanvdm_core.upscale.codeformer import CodeFormer
    from humanvdm_core.upscale.rrdbnet import RRDBNet

    torch.manual_seed(0)
    models = {
        "realesrgan_tiny": RRDBNet(4, num_feat=8, num_block=1, num_grow_ch=4),
        "realesrgan_real": RRDBNet(4),
        "codeformer_tiny": CodeFormer(nf=32, ch_mult=(1, 1, 1, 1), emb_dim=8, codebook_size=16, dim_embd=16,
                                      n_layers=1, connect=(32, 64, 128)),
        "codeformer_real": CodeFormer(),
        "rife_tiny": IFNet([(7, 16, 1), (12, 16, 1), (12, 8, 1), (12, 8, 1)]),
        "rife_real": IFNet([(7, 192, 8), (12, 128, 8), (12, 96, 8), (12, 64, 8)]),
    }
    paths, sizes = {}, {}
    for name, net in models.items():
        sizes[name] = round(sum(p.numel() for p in net.parameters()) / 1e6, 3)
        paths[name] = folder / f"{name}.pth"
        sd = net.state_dict()
        torch.save({"params_ema": sd} if not name.startswith("rife") else {f"module.{k}": v for k, v in sd.items()},
                   paths[name])
    for kind, cfgs in (("tiny", (pervfi.TINY, raft.TINY)), ("real", (pervfi.OFFICIAL, raft.OFFICIAL))):
        gen, flow = pervfi.save_random(folder / f"pervfi_{kind}.pth", folder / f"raft_{kind}.pth", *cfgs)
        paths[f"pervfi_{kind}"], paths[f"pervfi_{kind}_flow"] = gen, flow
        sizes[f"pervfi_{kind}"] = round(sum(v.numel() for v in torch.load(gen, weights_only=True).values()
                                            if v.dtype.is_floating_point) / 1e6, 3)
        sizes[f"pervfi_{kind}_raft"] = round(sum(v.numel() for v in torch.load(flow, weights_only=True).values()
                                                 if v.dtype.is_floating_point) / 1e6, 3)
    return paths, sizes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--probe", type=int, default=96, help="input size at which the real RRDBNet is timed")
    parser.add_argument("--full", action="store_true", help="time the real RRDBNet on the whole 576² frame")
    args = parser.parse_args()

    import tempfile

    import torch

    from humanvdm_core.interpolate import pervfi, rife
    from humanvdm_core.interpolate.core import BACKENDS as INTERP
    from humanvdm_core.interpolate.core import InterpolateOptions
    from humanvdm_core.upscale import codeformer, faces, rrdbnet
    from humanvdm_core.upscale.core import BACKENDS as UP
    from humanvdm_core.upscale.core import UpscaleOptions

    torch.set_num_threads(args.threads)
    frame0, frame1 = test_frame(0), np.roll(test_frame(0), 6, axis=1)
    res: dict = {"input": f"{SIZE}x{SIZE} RGBA", "target": TARGET, "torch_threads": args.threads,
                 "device": "cpu", "weights": "random (speed only)", "seconds_per_frame": {}}
    out = res["seconds_per_frame"]
    with tempfile.TemporaryDirectory() as tmp:
        paths, res["parameters_millions"] = save_models(Path(tmp))
        emb = UpscaleOptions(target_size=TARGET)
        out["upscale embedded"] = round(timed(lambda: UP["embedded"](frame0, emb), 3), 3)

        opts = UpscaleOptions(target_size=TARGET, realesrgan_weights=str(paths["realesrgan_tiny"]), tile=TILE)
        UP["realesrgan"](frame0, opts)  # load + warm up
        out["upscale realesrgan tiny (8 feat, 1 block)"] = round(timed(lambda: UP["realesrgan"](frame0, opts)), 3)

        real = rrdbnet.load(paths["realesrgan_real"])
        if args.full:
            ropts = UpscaleOptions(target_size=TARGET, realesrgan_weights=str(paths["realesrgan_real"]), tile=TILE)
            out["upscale realesrgan real (64 feat, 23 blocks)"] = round(timed(lambda: UP["realesrgan"](frame0, ropts)), 1)
            real_s = out["upscale realesrgan real (64 feat, 23 blocks)"]
        else:
            probe = np.ascontiguousarray(frame0[:args.probe, :args.probe, :3])
            t = timed(lambda: rrdbnet.upscale_rgb(real, probe, tile=0, tile_pad=0))
            over = tile_overhead(SIZE, TILE, TILE_PAD)
            real_s = t * (SIZE / args.probe) ** 2 * over
            out["upscale realesrgan real (64 feat, 23 blocks), extrapolated"] = round(real_s, 1)
            res["realesrgan_real_probe"] = {"input": f"{args.probe}x{args.probe}", "seconds": round(t, 2),
                                            "tile_overhead_at_576": round(over, 3)}

        rgb = frame0[..., :3]
        t_detect = timed(lambda: faces.detect_faces(rgb), 3)
        found = faces.detect_faces(rgb)
        res["faces_found_in_test_frame"] = len(found)
        out["face detection (mediapipe full range)"] = round(t_detect, 3)
        copts = UpscaleOptions(target_size=TARGET, realesrgan_weights=str(paths["realesrgan_tiny"]),
                               codeformer_weights=str(paths["codeformer_tiny"]), tile=TILE)
        UP["codeformer"](frame0, copts)
        out["upscale codeformer tiny (+ tiny realesrgan background)"] = round(timed(lambda: UP["codeformer"](frame0, copts)), 3)
        cf = codeformer.load(paths["codeformer_real"])
        crop = np.random.default_rng(0).random((512, 512, 3)).astype(np.float32)
        t_face = timed(lambda: codeformer.restore_face(cf, crop, 0.7))
        out["codeformer real, one 512² face"] = round(t_face, 1)
        out["upscale codeformer real, estimate (real background + detection + faces found)"] = round(
            real_s + t_detect + max(len(found), 1) * t_face, 1)

        iopts = InterpolateOptions()
        out["interpolate embedded (flow), one in-between frame"] = round(
            timed(lambda: INTERP["embedded"](frame0, frame1, [0.5], iopts), 3), 3)
        for kind in ("tiny", "real"):
            net = rife.load(paths[f"rife_{kind}"])
            rife.interpolate_pair(net, frame0, frame1, [0.5])
            out[f"interpolate rife {kind}, one in-between frame"] = round(
                timed(lambda net=net: rife.interpolate_pair(net, frame0, frame1, [0.5]), 3), 3)
        for kind in ("tiny", "real"):
            model = pervfi.load(paths[f"pervfi_{kind}"], paths[f"pervfi_{kind}_flow"])
            pervfi.interpolate_pair(model, frame0[:64, :64], frame1[:64, :64])  # warm up
            out[f"interpolate pervfi {kind} (+ RAFT), one in-between frame"] = round(
                timed(lambda model=model: pervfi.interpolate_pair(model, frame0, frame1), 1 if kind == "real" else 2), 2)

    per_orbit = {
        "upscale 21 frames, realesrgan real (s)": round(21 * real_s),
        "interpolate 21 -> 81, rife real (s)": round(60 * out["interpolate rife real, one in-between frame"]),
        "interpolate 21 -> 81, pervfi real (s)": round(
            60 * out["interpolate pervfi real (+ RAFT), one in-between frame"]),
    }
    res["per_orbit_estimate_cpu"] = per_orbit
    cmd = "python benchmarks/bench_model_backends.py " + " ".join(sys.argv[1:])
    path = save_result("model_backends", res, cmd.strip())
    print(path)
    for k, v in {**out, **per_orbit}.items():
        print(f"{v:>10}  {k}")


if __name__ == "__main__":
    main()
