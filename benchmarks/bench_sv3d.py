"""Speed and memory of the SV3D backend of ``diffuse`` on this machine (random weights: speed only).

- ``tiny``: the whole ``generate_orbit`` (CLIP, VAE encode, EDM Euler with triangle CFG, chunked
  decoding) with the tiny test checkpoint in the official layout, 21 frames at 64², ``--steps``.
- ``real``: the real-size video UNet (``SV3D_CONFIG``, 1.5 B parameters, random weights) -- one
  forward pass over the 21 frames at ``--size`` (latents ``size/8``), i.e. half of one sampling step
  (classifier-free guidance runs the conditional and unconditional halves); the estimate for a
  whole orbit is ``2 x steps x`` that. Peak RSS is the process's.

Run:  .venv/bin/python -m benchmarks.bench_sv3d [--steps 10] [--size 576] [--threads 2]
Writes benchmarks/results/sv3d.json.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import save_result  # noqa: E402


def main() -> None:
    import torch

    from humanvdm_core.models import sv3d, sv3d_unet

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--size", type=int, default=576)
    parser.add_argument("--frames", type=int, default=21)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--skip-real", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    out: dict = {"threads": args.threads, "device": "cpu", "weights": "random (speed only)"}

    with tempfile.TemporaryDirectory() as tmp:
        ckpt = sv3d.write_tiny_checkpoint(Path(tmp) / "sv3d_p.safetensors", "sv3d_p")
        model = sv3d.build(ckpt)
        image = np.ones((64, 64, 4), np.float32)
        image[16:48, 24:40, :3] = 0.3
        sv3d.generate_orbit(model, image, steps=1, seed=0)  # warm-up
        t0 = time.perf_counter()
        frames = sv3d.generate_orbit(model, image, steps=args.steps, seed=0)
        out["tiny"] = {"frames": len(frames), "size": 64, "steps": args.steps,
                       "seconds": round(time.perf_counter() - t0, 2)}
    print(out["tiny"], flush=True)

    if not args.skip_real:
        t0 = time.perf_counter()
        with torch.device("meta"):
            unet = sv3d_unet.VideoUNet(sv3d_unet.SV3D_CONFIG)
        unet = unet.to_empty(device="cpu")
        for p in unet.parameters():  # random weights, small enough to keep activations finite
            torch.nn.init.normal_(p, std=0.02)
        unet.eval()
        n_params = sum(p.numel() for p in unet.parameters())
        build_s = time.perf_counter() - t0
        T, h = args.frames, args.size // 8
        cfg = sv3d_unet.SV3D_CONFIG
        x = torch.randn(T, cfg["in_channels"], h, h)
        t = torch.full((T,), 0.25 * float(np.log(700.0)))
        ctx = torch.randn(T, 1, cfg["context_dim"])
        y = torch.randn(T, cfg["adm_in_channels"])
        ioi = torch.zeros(1, T)
        with torch.no_grad():
            t0 = time.perf_counter()
            pred = unet(x, t, ctx, y, T, ioi)
            forward_s = time.perf_counter() - t0
        assert pred.shape == (T, cfg["out_channels"], h, h) and torch.isfinite(pred).all()
        out["real"] = {"parameters": n_params, "frames": T, "size": args.size, "latent": h,
                       "build_s": round(build_s, 1), "unet_forward_s": round(forward_s, 1),
                       "estimated_orbit_s_50_steps": round(2 * 50 * forward_s),
                       "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}
        print(out["real"], flush=True)
    path = save_result("sv3d", out, "python -m benchmarks.bench_sv3d " + " ".join(sys.argv[1:]))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
