#!/usr/bin/env sh
# System libraries pip cannot install: Python >= 3.10 with venv, and EGL/GL for headless rendering.
# Says exactly what to install instead of failing later inside a stage.
set -u
fail=0
if ! command -v python3 >/dev/null 2>&1 || ! python3 -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then
  echo "error: Python 3.10 or newer is needed (Debian/Ubuntu: apt-get install python3 python3-venv)"; fail=1
elif ! python3 -c 'import venv, ensurepip' >/dev/null 2>&1; then
  echo "error: Python's venv module is missing (Debian/Ubuntu: apt-get install python3-venv)"; fail=1
fi
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1" || ls /usr/lib/*/"$1"* /usr/lib/"$1"* /usr/lib64/"$1"* >/dev/null 2>&1; }
missing=""
have_lib libEGL.so.1 || missing="$missing libegl1"
have_lib libGL.so.1 || missing="$missing libgl1"
# A GPU driver's EGL (NVIDIA) or Mesa's software one (llvmpipe) must be there to make a context.
if ! have_lib libEGL_nvidia.so && ! have_lib libEGL_mesa.so; then missing="$missing libegl-mesa0 libgl1-mesa-dri"; fi
if [ -n "$missing" ]; then
  echo "error: headless rendering (moderngl + EGL) needs system libraries that are missing."
  echo "       Debian/Ubuntu: sudo apt-get install$missing"
  echo "       Fedora: sudo dnf install mesa-libEGL mesa-libGL mesa-dri-drivers"
  fail=1
fi
exit $fail
