"""``python -m humanvdm_core.doctor``: check that this machine can run the pipeline.

Checks the headless OpenGL context (moderngl + EGL) the renderer needs and reports torch's device.
Exits non-zero with the fix spelled out when something is missing.
"""

from __future__ import annotations

import sys


def check_egl() -> str:
    import moderngl

    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as e:  # the EGL loader's errors are many and vague; report them with the fix
        raise RuntimeError(
            f"cannot create a headless OpenGL context through EGL ({e}). Install the system's EGL/GL "
            "libraries: Debian/Ubuntu `sudo apt-get install libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri` "
            "(with an NVIDIA GPU, its driver's EGL library is used instead)."
        ) from None
    try:
        return f"{ctx.info['GL_RENDERER']} (OpenGL {ctx.version_code})"
    finally:
        ctx.release()


def main() -> int:
    try:
        renderer = check_egl()
    except RuntimeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    import torch

    device = f"CUDA ({torch.cuda.get_device_name(0)})" if torch.cuda.is_available() else "CPU"
    print(f"humanvdm: rendering on {renderer}; torch {torch.__version__} on {device}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
