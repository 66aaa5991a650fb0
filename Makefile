# One-command entry points. Every target installs what it needs into .venv first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo serve test test-fast bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# The pinned CPU build first: a bare 'torch' requirement would pull CUDA wheels.
	# Users with a GPU install their own torch build before running make.
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e ".[dev,realsense,ray,record3d]"
	# Compile the numba kernels into numba's disk cache now, not in a user's first frame.
	$(BIN)/python -c "import slam.kernels as k; print(f'numba kernels ready in {k.warm_up():.1f} s')"
	touch $(STAMP)

setup: $(STAMP)

# The HTTP port: `make demo PORT=8001`, or VOXFUSION_PORT in the environment (default 8000;
# the demo moves on to the next free port when it is taken).
PORT_FLAG := $(if $(PORT),--port $(PORT))
# The 3D viewer's own port: `make demo VIEWER_PORT=8081`, or VOXFUSION_VIEWER_PORT (default
# 8080; -1 turns the viewer off). The page reaches it through /viewer on the HTTP port.
VIEWER_PORT_FLAG := $(if $(VIEWER_PORT),--viewer-port $(VIEWER_PORT))

demo: $(STAMP)
	$(BIN)/voxfusion demo $(PORT_FLAG) $(VIEWER_PORT_FLAG)

serve: $(STAMP)
	$(BIN)/voxfusion serve $(PORT_FLAG) $(VIEWER_PORT_FLAG)

test: $(STAMP)
	bash scripts/browser-deps.sh
	$(BIN)/python -m pytest -q

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not browser and not slow"

bench: $(STAMP)
	bash scripts/bench-deps.sh
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
