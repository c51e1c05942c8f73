"""Benchmark: the GPU checks -- gsplat against our rasterizer, the ``full`` preset's training step, SV3D fp16.

Needs a CUDA device: without one it says so and exits 0 (``make bench`` runs every benchmark), unless
``--smoke`` asks for tiny sizes on the CPU (a check of this script). The sections, in this order (the
SV3D ones first, so that gsplat's first-use compile, started beside this script, overlaps them;
``--gsplat-ready FILE`` names the file that appears when it is done):

- ``sv3d``: the whole ``generate_orbit`` with the tiny test checkpoint on CUDA (the fp16 autocast path
  runs end to end, frames finite); then the real-size video UNet (``SV3D_CONFIG``, 1.5 B parameters,
  random weights: speed and numerics, not quality) over one sampling step's batch (2 x 21 frames, the
  two CFG halves) at 576² (latents 72²): fp32, fp16 autocast (what ``diffuse`` uses on CUDA) and bf16
  autocast -- median seconds, peak GPU memory, and each low-precision output's relative L2 error against
  fp32. The orbit estimate is ``50 x`` the fp16 step (the VAE and CLIP are not timed).
- ``sv3d_orbit`` (not in the default ``--sections``): the whole ``generate_orbit`` with every part at
  SV3D_p's real size (the UNet, OpenCLIP ViT-H/14, sgm's VAE encoder and video decoder; random
  weights): seconds for one orbit of 21 frames at 576² and 50 steps, peak GPU memory.
- ``rasterize``: ``rasterize_gaussians`` with ``backend="torch"`` (our tiled PyTorch path, on CUDA) and
  ``"gsplat"`` on :mod:`benchmarks.bench_rasterize`'s body-shaped scenes: agreement (image PSNR and max
  difference of gsplat against ours, alpha, the cosine similarity of each parameter's gradient) and speed
  (median forward and forward+backward seconds, peak GPU memory) at 200k Gaussians 576² / 1080² and
  500k 1080².
- ``train_step``: one optimisation step of the ``full`` preset's shape -- 2 views at 1080², 0.8 L1 +
  0.2 (1 - SSIM), backward, Adam over means/quats/scales/opacities/colours -- median seconds at 200k and
  500k (its ``max_gaussians``) Gaussians, and ``30000 x`` that: the rasterizer's and the loss's share of
  a ``full`` splat-optimize run (the MLP decoder, the skinning and densification are not in it).
- ``stage`` (not in the default ``--sections``; needs ``--orbit DIR --body FILE``): the real stages,
  each its own process as the scheduler runs it -- ``upscale`` and ``interpolate`` (embedded backends)
  on a ``diffuse`` orbit, then ``splat-optimize`` with the ``full`` preset (gsplat when it compiled) for
  ``--iterations`` steps (0: the preset's 30,000) on those frames and the ``fit-smpl`` body (written
  with ``uv_resolution`` 569, the preset's, so no body model is needed there): each stage's seconds,
  the training's seconds per step and its 30,000-step estimate, the Gaussian count and the training
  PSNR; the stages' logs and the turntable GIF are copied beside ``--out``, and with ``--keep-gaussians
  FILE`` the trained Gaussians (``gaussians.npz``'s arrays that render them, compressed) to FILE, for
  ``bench_protocol --gaussians``. ``--work DIR`` keeps the stage section's scratch folder and reuses the
interpolated frames already there; ``--until interpolate`` stops before training: so a first call
upscales and interpolates while gsplat compiles, and a second call on the same machine trains only (the
folder, and ``TORCH_EXTENSIONS_DIR``, must be paths git ignores there, or the next call's copy of the
working tree removes them).

Writes ``--out`` (default ``benchmarks/results/gpu.json``) with the device named.
Run: ``python -m benchmarks.bench_gpu [--gsplat-ready /tmp/gsplat_ready] [--out F] [--smoke]``, or
``--sections stage --orbit DIR --body body.npz [--iterations N] [--keep-gaussians FILE]``.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.bench_rasterize import body_cloud, orbit_camera  # noqa: E402


def _sync() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _timed(fn, repeats: int, budget_s: float = 20.0) -> tuple[float, list[float]]:
    """Median seconds of ``fn()`` over ``repeats`` calls after one warm-up (synchronised); a warm-up
    longer than ``budget_s`` is the one run."""
    t0 = time.perf_counter()
    fn()
    _sync()
    first = time.perf_counter() - t0
    if first > budget_s:
        return round(first, 4), [round(first, 4)]
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync()
        runs.append(time.perf_counter() - t0)
    return round(statistics.median(runs), 4), [round(r, 4) for r in runs]


def _peak_mb(reset: bool = False) -> float:
    import torch

    if not torch.cuda.is_available():
        return float("nan")
    if reset:
        torch.cuda.reset_peak_memory_stats()
        return 0.0
    return round(torch.cuda.max_memory_allocated() / 2**20, 1)


def sv3d_section(dev, smoke: bool) -> dict:
    import tempfile

    import numpy as np
    import torch

    from humanvdm_core.models import sv3d, sv3d_unet

    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        model = sv3d.build(sv3d.write_tiny_checkpoint(Path(tmp) / "sv3d_p.safetensors", "sv3d_p"))
        image = np.ones((64, 64, 4), np.float32)
        image[16:48, 24:40, :3] = 0.3
        t0 = time.perf_counter()
        frames = sv3d.generate_orbit(model, image, steps=4, seed=0)
        _sync()
        out["tiny_orbit"] = {"device": str(model.device), "frames": len(frames), "steps": 4,
                             "finite": bool(all(np.isfinite(f).all() for f in frames)),
                             "seconds": round(time.perf_counter() - t0, 2)}
        del model
    print("sv3d tiny", out["tiny_orbit"], flush=True)

    cfg = sv3d_unet.SV3D_CONFIG
    with torch.device("meta"):
        unet = sv3d_unet.VideoUNet(cfg)
    unet = unet.to_empty(device=dev)
    g = torch.Generator(device=dev).manual_seed(0)
    with torch.no_grad():
        for p in unet.parameters():
            p.normal_(0.0, 0.02, generator=g)
    unet.eval()
    frames, size = (2, 64) if smoke else (21, 576)
    batch, h = 2 * frames, size // 8
    x = torch.randn(batch, cfg["in_channels"], h, h, device=dev, generator=g)
    t = torch.full((batch,), 0.25 * math.log(700.0), device=dev)
    ctx = torch.randn(batch, 1, cfg["context_dim"], device=dev, generator=g)
    y = torch.randn(batch, cfg["adm_in_channels"], device=dev, generator=g)
    ioi = torch.zeros(2, frames, device=dev)
    out["unet"] = {"parameters": sum(p.numel() for p in unet.parameters()), "batch": batch, "size": size,
                   "latent": h, "tf32": bool(torch.backends.cuda.matmul.allow_tf32)}
    preds = {}
    for name, dtype in (("fp32", None), ("fp16", torch.float16), ("bf16", torch.bfloat16)):
        if dtype is not None and dev.type != "cuda":
            continue

        def step(dtype=dtype, name=name) -> None:
            ctx_mgr = torch.autocast("cuda", dtype=dtype) if dtype is not None else torch.autocast("cuda", enabled=False)
            with torch.no_grad(), ctx_mgr:
                preds[name] = unet(x, t, ctx, y, frames, ioi).float()

        _peak_mb(reset=True)
        try:
            med, runs = _timed(step, 1 if smoke else 3)
            row = {"step_s": med, "runs_s": runs, "peak_gpu_mb": _peak_mb(), "finite": bool(torch.isfinite(preds[name]).all())}
        except torch.OutOfMemoryError as exc:
            row = {"error": f"out of memory: {exc}"[:300]}
        out["unet"][name] = row
        print("sv3d unet", name, row, flush=True)
    ref = preds.get("fp32")
    for name in ("fp16", "bf16"):
        if ref is not None and name in preds:
            err = (preds[name] - ref).norm() / ref.norm()
            out["unet"][name]["relative_l2_vs_fp32"] = round(float(err), 5)
    if "fp16" in out["unet"] and "step_s" in out["unet"]["fp16"]:
        out["orbit_estimate_s_50_steps_fp16"] = round(50 * out["unet"]["fp16"]["step_s"], 1)
    return out


def sv3d_orbit_section(dev, smoke: bool) -> dict:
    """The whole ``generate_orbit`` (CLIP, VAE encode, 50 EDM steps with CFG, chunked video decoding) with
    every part at SV3D_p's real size and random weights (timing and memory, not quality)."""
    import numpy as np
    import torch

    from humanvdm_core.models import openclip_vision, sv3d, sv3d_unet, sv3d_vae

    widths = (32, 64) if smoke else (128, 256, 512, 512)  # sgm's VAE: ch 128, ch_mult (1, 2, 4, 4)
    with torch.device("meta"):
        unet = sv3d_unet.VideoUNet(sv3d_unet.tiny_config() if smoke else sv3d_unet.SV3D_CONFIG)
        clip = (openclip_vision.OpenCLIPImageEmbedder(width=64, layers=1, heads=1, mlp_width=128,
                                                     output_dim=unet.config["context_dim"]) if smoke
                else openclip_vision.OpenCLIPImageEmbedder())  # ViT-H/14, output 1024
        encoder = sv3d_vae.CondFrameEncoder(widths[0], widths, 2, 4, 4)
        decoder = sv3d_vae.VideoFirstStage(widths, 2, 4)
    model = sv3d.SV3D("sv3d_p", unet, clip, encoder, decoder).to_empty(device=dev)
    g = torch.Generator(device=dev).manual_seed(0)
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.02, generator=g)
        for name, buf in model.named_buffers():  # CLIP's normalisation constants
            if name.endswith("mean"):
                buf.copy_(torch.tensor(openclip_vision.CLIP_MEAN).view(1, 3, 1, 1))
            elif name.endswith("std"):
                buf.copy_(torch.tensor(openclip_vision.CLIP_STD).view(1, 3, 1, 1))
    model.eval()
    size = 64 if smoke else sv3d.SIZE
    image = np.ones((size, size, 4), np.float32)
    image[size // 4:3 * size // 4, 3 * size // 8:5 * size // 8, :3] = 0.3
    steps = 2 if smoke else sv3d.DEFAULT_STEPS
    sv3d.generate_orbit(model, image, steps=1, seed=0)  # warm-up (kernels, allocator)
    _sync()
    _peak_mb(reset=True)
    t0 = time.perf_counter()
    frames = sv3d.generate_orbit(model, image, steps=steps, seed=0)
    _sync()
    out = {"parameters": sum(p.numel() for p in model.parameters()), "frames": len(frames), "size": size,
           "steps": steps, "seconds": round(time.perf_counter() - t0, 2), "peak_gpu_mb": _peak_mb(),
           "finite": bool(np.isfinite(frames).all())}
    print("sv3d orbit", out, flush=True)
    return out


def _scene(n: int, size: int, dev, isotropic: bool):
    viewmats, Ks = orbit_camera(size)
    return [t.to(dev) for t in body_cloud(n, isotropic=isotropic)], viewmats.to(dev), Ks.to(dev)


def _render(params, viewmats, Ks, size: int, backend: str, grad: bool):
    import torch

    from humanvdm_core.splat import rasterize_gaussians

    leaves = [p.detach().clone().requires_grad_(grad) for p in params]
    bg = torch.ones(viewmats.shape[0], 3, device=viewmats.device)
    colors, alphas, _ = rasterize_gaussians(*leaves, viewmats, Ks, size, size, backgrounds=bg, backend=backend)
    if grad:
        (colors.square().mean() + alphas.mean()).backward()
    return colors.detach(), alphas.detach(), [p.grad for p in leaves] if grad else None


def rasterize_section(dev, backends: list[str], smoke: bool) -> dict:
    import torch

    out: dict = {"agreement": [], "speed": []}
    names = ("means", "quats", "scales", "opacities", "colors")
    for n, size, iso in ([(2000, 64, False)] if smoke else [(200_000, 576, False), (200_000, 1080, True)]):
        if "gsplat" not in backends:
            break
        params, viewmats, Ks = _scene(n, size, dev, iso)
        a_col, a_alpha, a_grads = _render(params, viewmats, Ks, size, "torch", True)
        b_col, b_alpha, b_grads = _render(params, viewmats, Ks, size, "gsplat", True)
        mse = float((a_col - b_col).square().mean())
        row = {"n_gaussians": n, "size": size, "scene": "iso" if iso else "aniso",
               "psnr_gsplat_vs_torch_db": round(-10 * math.log10(max(mse, 1e-20)), 2),
               "max_abs_color_diff": round(float((a_col - b_col).abs().max()), 5),
               "max_abs_alpha_diff": round(float((a_alpha - b_alpha).abs().max()), 5)}
        for name, ga, gb in zip(names, a_grads, b_grads, strict=True):
            cos = torch.nn.functional.cosine_similarity(ga.flatten().double(), gb.flatten().double(), dim=0)
            row[f"grad_cosine_{name}"] = round(float(cos), 5)
            row[f"grad_rel_l2_{name}"] = round(float((ga - gb).norm() / gb.norm().clamp_min(1e-30)), 5)
        out["agreement"].append(row)
        print("agree", row, flush=True)
    configs = [(2000, 64)] if smoke else [(200_000, 576), (200_000, 1080), (500_000, 1080)]
    for backend in backends:
        for n, size in configs:
            if backend == "torch" and n > 200_000:
                continue  # minutes on our PyTorch path; the 200k rows give its ratio
            scene = (*_scene(n, size, dev, True), size, backend)
            _peak_mb(reset=True)
            reps = 1 if smoke else (3 if backend == "torch" else 10)
            fwd, fwd_runs = _timed(functools.partial(_render, *scene, False), reps)
            fb, fb_runs = _timed(functools.partial(_render, *scene, True), reps)
            row = {"backend": backend, "n_gaussians": n, "size": size, "forward_s": fwd, "forward_backward_s": fb,
                   "forward_runs_s": fwd_runs, "forward_backward_runs_s": fb_runs, "peak_gpu_mb": _peak_mb()}
            out["speed"].append(row)
            print("speed", row, flush=True)
    return out


def _train_step(leaves: list, opt, viewmats, Ks, size: int, bg, target, backend: str) -> None:
    """One step of ``opt`` on 0.8 L1 + 0.2 (1 - SSIM) of the ``leaves``' render against ``target``."""
    import torch

    from humanvdm_core.metrics import ssim_map
    from humanvdm_core.splat import rasterize_gaussians

    opt.zero_grad(set_to_none=True)
    img, _, _ = rasterize_gaussians(*leaves, viewmats, Ks, size, size, backgrounds=bg, backend=backend)
    loss = 0.8 * (img - target).abs().mean() + 0.2 * (1.0 - ssim_map(img, target).mean())
    loss.backward()
    opt.step()
    with torch.no_grad():
        leaves[3].clamp_(0.01, 1.0)
        leaves[2].clamp_(min=1e-4)


def train_section(dev, backends: list[str], smoke: bool) -> dict:
    import torch

    from humanvdm_core.splat import rasterize_gaussians

    out: dict = {"iterations_full": 30000, "views_per_step": 2, "rows": []}
    size = 64 if smoke else 1080
    for backend in backends:
        for n in ([2000] if smoke else ([200_000] if backend == "torch" else [200_000, 500_000])):
            params = [t.to(dev) for t in body_cloud(n, isotropic=True)]
            cams = [orbit_camera(size, azimuth_deg=a) for a in (30.0, 120.0)]
            viewmats = torch.cat([c[0] for c in cams]).to(dev)
            Ks = torch.cat([c[1] for c in cams]).to(dev)
            bg = torch.ones(2, 3, device=dev)
            with torch.no_grad():
                target, _, _ = rasterize_gaussians(*params, viewmats, Ks, size, size, backgrounds=bg, backend=backend)
                target = target.clamp(0, 1).flip(-1)  # a different picture to fit
            leaves = [p.detach().clone().requires_grad_(True) for p in params]
            opt = torch.optim.Adam(leaves, lr=1e-3)
            step = functools.partial(_train_step, leaves, opt, viewmats, Ks, size, bg, target, backend)
            _peak_mb(reset=True)
            med, runs = _timed(step, 1 if smoke else (3 if backend == "torch" else 20))
            row = {"backend": backend, "n_gaussians": n, "size": size, "step_s": med, "runs_s": runs,
                   "peak_gpu_mb": _peak_mb(), "estimate_30000_steps_min": round(30000 * med / 60, 1)}
            out["rows"].append(row)
            print("train", row, flush=True)
    return out


def _stage(name: str, argv: list[str], log_path: Path) -> tuple[float, str]:
    """Run stage ``name`` as its own process (``python -m stages.NAME ARGV``): wall seconds and its log."""
    import subprocess

    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", f"stages.{name.replace('-', '_')}", *argv], cwd=REPO,
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    log_path.write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        raise RuntimeError(f"stage {name} failed ({proc.returncode}): {(proc.stdout + proc.stderr)[-1500:]}")
    return wall, proc.stdout + proc.stderr


def stage_section(orbit: Path, body: Path, iterations: int, out_dir: Path, smoke: bool,
                  keep_gaussians: Path | None = None, work: Path | None = None, until: str = "",
                  before_training=None) -> dict:
    """upscale -> interpolate -> splat-optimize (``full``) as the pipeline runs them; see the docstring.

    ``work``: a kept scratch folder whose interpolated frames, when there, are reused (the stages before
    training are then not run again); ``until="interpolate"`` stops before training; ``before_training()``
    is called just before ``splat-optimize`` starts (the wait for gsplat's compile).
    """
    import re
    import shutil
    import tempfile

    keep_work = work is not None
    work = Path(work) if keep_work else Path(tempfile.mkdtemp(prefix="bench_gpu_stage_"))
    preset = "tiny" if smoke else "full"
    out: dict = {"orbit": str(orbit), "preset": preset, "stages": {}}
    logs = out_dir / "gpu_stage_logs"
    logs.mkdir(parents=True, exist_ok=True)
    if keep_work and (work / "interp" / "cameras.npz").exists():
        out["stages"]["reused_frames"] = str(work / "interp")
    else:
        out["stages"]["upscale_s"] = round(_stage("upscale", [
            "--frames", str(orbit), "--out-frames", str(work / "up"), "--target-size", "128" if smoke else "1080"],
            logs / "upscale.log")[0], 1)
        out["stages"]["interpolate_s"] = round(_stage("interpolate", [
            "--frames", str(work / "up"), "--out-frames", str(work / "interp")], logs / "interpolate.log")[0], 1)
    if until == "interpolate":
        print("stage", out, flush=True)
        return out
    if before_training is not None:
        before_training()
    argv = ["--frames", str(work / "interp"), "--body", str(body), "--orbit", str(orbit),
            "--out-gaussians", str(work / "gaussians"), "--preset", preset]
    if smoke:  # the tiny preset's UV map is the body file's, so that no body model is needed either
        import numpy as np

        argv += ["--uv-resolution", str(int(np.load(body)["uv_resolution"]))]
    if iterations:
        argv += ["--iterations", str(iterations)]
    wall, text = _stage("splat-optimize", argv, logs / "splat_optimize.log")
    out["stages"]["splat_optimize_s"] = round(wall, 1)
    trained = re.search(r"trained in ([0-9.]+) s", text)
    header = re.search(r"preset (\w+), template (.*?): (\d+) Gaussians, (\d+) views at (\d+)².*?(\d+) iterations on (\w+)",
                       text)
    train_log = json.loads((work / "gaussians" / "train_log.json").read_text())
    steps = int(header.group(6)) if header else iterations
    out["splat"] = {"header": header.group(0) if header else None, "train_s": float(trained.group(1)) if trained else None,
                    "iterations": steps, "num_gaussians": train_log["num_gaussians"],
                    "initial_gaussians": train_log["initial_gaussians"], "train_psnr": train_log["train_psnr"],
                    "device": train_log["device"], "densify_steps": train_log["densify_steps"],
                    "gsplat_missing_warning": "gsplat does not import" in text}
    # the steady rate: the second half of training (after the last densify step, at the final count), from
    # the stage's progress lines "iter N/M loss L  T s" (T: seconds since training began)
    marks = [(int(m.group(1)), float(m.group(2))) for m in re.finditer(r"iter +(\d+)/\d+ +loss \S+ +([0-9.]+) s", text)]
    late = [(i, t) for i, t in marks if i >= steps // 2]
    if len(late) >= 2 and late[-1][0] > late[0][0]:
        per = (late[-1][1] - late[0][1]) / (late[-1][0] - late[0][0])
        out["splat"]["s_per_step_second_half"] = round(per, 5)
        out["splat"]["estimate_30000_steps_min"] = round(30000 * per / 60, 1)
    gif = work / "gaussians" / "turntable.gif"
    if gif.exists():
        shutil.copy(gif, out_dir / "gpu_stage_turntable.gif")
    if keep_gaussians:
        import numpy as np

        with np.load(work / "gaussians" / "gaussians.npz") as g:
            keep = ("__schema__", "__schema_version__", "means", "quats", "scales", "opacities", "colors")
            np.savez_compressed(keep_gaussians, **{k: g[k] for k in keep})
    if not keep_work:
        shutil.rmtree(work, ignore_errors=True)
    print("stage", out, flush=True)
    return out


def main() -> None:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "gpu.json"))
    parser.add_argument("--gsplat-ready", default="", help="file that appears when gsplat's compile is done")
    parser.add_argument("--wait", type=float, default=420.0, help="seconds to wait for that file at most")
    parser.add_argument("--sections", default="sv3d,rasterize,train_step")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes (a CPU check of this script)")
    parser.add_argument("--orbit", type=Path, help="stage section: a diffuse orbit folder (frames, cameras, proxy)")
    parser.add_argument("--body", type=Path, help="stage section: a fit-smpl body.npz with uv_resolution 569")
    parser.add_argument("--iterations", type=int, default=0, help="stage section: training steps (0: the preset's)")
    parser.add_argument("--keep-gaussians", type=Path, help="stage section: save the trained Gaussians here (.npz)")
    parser.add_argument("--work", type=Path, help="stage section: a kept scratch folder; its interpolated frames, "
                        "when there, are reused (a second call trains only)")
    parser.add_argument("--until", choices=["", "interpolate"], default="",
                        help="stage section: stop after interpolate (run while gsplat compiles)")
    args = parser.parse_args()
    if "stage" in args.sections.split(",") and not (args.orbit and args.body):
        parser.error("--sections stage needs --orbit and --body")
    if not torch.cuda.is_available() and not args.smoke:  # `make bench` on a machine without a GPU
        print("bench_gpu: no CUDA device, skipped (results/gpu.json keeps the last GPU run; --smoke runs "
              "tiny sizes on the CPU)")
        return
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    doc: dict = {"benchmark": "gpu", "command": "python -m benchmarks.bench_gpu " + " ".join(sys.argv[1:]),
                 "date": time.strftime("%Y-%m-%d"), "python": platform.python_version(), "torch": torch.__version__,
                 "cuda": torch.version.cuda, "device": torch.cuda.get_device_name() if dev.type == "cuda" else "cpu",
                 "result": {}}
    t_start = time.perf_counter()

    def save() -> None:
        doc["wall_s"] = round(time.perf_counter() - t_start, 1)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")

    sections = args.sections.split(",")

    def run(name: str, fn, *fn_args) -> None:
        """Section ``name`` when asked for: its result, or the error it raised, saved at once."""
        if name in sections:
            try:
                doc["result"][name] = fn(*fn_args)
            except Exception:
                doc["result"][name] = {"error": traceback.format_exc()[-2000:]}
            save()

    run("sv3d", sv3d_section, dev, args.smoke)
    run("sv3d_orbit", sv3d_orbit_section, dev, args.smoke)
    backends = ["torch"]

    def wait_for_gsplat() -> None:
        """Wait for ``--gsplat-ready`` (once), then record whether gsplat's kernels load."""
        if not args.gsplat_ready or "gsplat" in doc["result"]:
            return
        t0 = time.perf_counter()
        while not Path(args.gsplat_ready).exists() and time.perf_counter() - t0 < args.wait:
            time.sleep(2)
        build = {"waited_s": round(time.perf_counter() - t0, 1)}
        try:
            import gsplat

            build.update(version=gsplat.__version__)
            from gsplat.cuda._backend import _C

            build["compiled"] = _C is not None
            if _C is not None:
                backends.append("gsplat")
        except Exception:
            build["error"] = traceback.format_exc()[-2000:]
        doc["result"]["gsplat"] = build
        print("gsplat", build, flush=True)
        save()

    if {"rasterize", "train_step"} & set(sections):
        wait_for_gsplat()
    run("rasterize", rasterize_section, dev, backends, args.smoke)
    run("train_step", train_section, dev, backends, args.smoke)
    run("stage", stage_section, args.orbit, args.body, args.iterations, Path(args.out).parent, args.smoke,
        args.keep_gaussians, args.work, args.until, wait_for_gsplat)
    print(f"wrote {args.out} in {doc['wall_s']} s", flush=True)


if __name__ == "__main__":
    main()
