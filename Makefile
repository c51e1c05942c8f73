# The only commands a newcomer needs:
#   make reconstruct INPUT=photo.png     install what is missing, then run the pipeline on a photo (or a folder)
#   make test                            install what is missing, then run the test suite
# Others: make setup | lint | bench | experiments | doctor | clean-venv

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
JOBS   ?= 1
ARGS   ?=
# test files run side by side, one worker per core this process may use (0: one process, no workers)
TEST_WORKERS ?= $(shell $(PYTHON) -c "import os; n = len(os.sched_getaffinity(0)); print(n if n > 1 else 0)" 2>/dev/null || echo 0)

.PHONY: setup reconstruct test lint bench experiments doctor clean-venv

setup: $(STAMP)

# Re-runs only when pyproject.toml changes, so an installed machine pays nothing.
$(STAMP): pyproject.toml
	@./scripts/check_system.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@$(PY) -m pip install -q --upgrade pip >/dev/null
	@# torch: keep one that is installed; with an NVIDIA GPU take PyPI's default (CUDA) build,
	@# without one pin the CPU release the project is tested with.
	@if ! $(PY) -c "import torch" 2>/dev/null; then \
	  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then \
	    echo "installing torch (CUDA build)"; $(PY) -m pip install -q "torch>=2.3"; \
	  else \
	    echo "installing torch==2.13.0 (no CUDA GPU found)"; $(PY) -m pip install -q "torch==2.13.0"; \
	  fi; \
	fi
	@# gsplat (the CUDA rasterizer, extra "cuda") only where an NVIDIA GPU is present.
	@if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then \
	  $(PY) -m pip install -q -e ".[dev,viewer,cuda]"; \
	else \
	  $(PY) -m pip install -q -e ".[dev,viewer]"; \
	fi
	@# mediapipe's metadata pins numpy<2 and a second OpenCV; it runs fine on ours (see pyproject.toml).
	@$(PY) -m pip install -q --no-deps "mediapipe==0.10.21"
	@$(PY) -m humanvdm_core.doctor
	@touch $(STAMP)

reconstruct: setup
	@if [ -z "$(INPUT)" ]; then echo "usage: make reconstruct INPUT=photo.png (or a folder of photos)"; exit 2; fi
	$(VENV)/bin/humanvdm run "$(INPUT)" --jobs $(JOBS) $(ARGS)

test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile $(ARGS)

lint: setup
	$(VENV)/bin/ruff check .

bench: setup
	$(PY) -m benchmarks.run $(BENCH)

# The paper's experiments and ours through the scheduler's cache (benchmarks/README.md); ARGS=--quick: tiny settings
experiments: setup
	$(PY) -m benchmarks.experiments $(ARGS)

doctor: setup
	$(PY) -m humanvdm_core.doctor

clean-venv:
	rm -rf $(VENV)
