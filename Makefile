# `make demo` and `make test` are the two entry points (README). Both create .venv and install everything first.
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO   ?= out/demo
# PyTorch 2.13.0 CPU build (an unpinned torch pulls a multi-GB CUDA build).
TORCH  ?= torch==2.13.0

.PHONY: install sysdeps demo test clean

install: $(STAMP)

# Offscreen rendering needs Mesa's EGL (llvmpipe). Installed from Debian when missing and we are root.
sysdeps:
	@if ! ldconfig -p | grep -q libEGL_mesa.so.0 || ! ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1; then \
		if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri; \
		else echo "missing Mesa EGL: sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri" >&2; exit 1; fi; fi

$(STAMP): setup.py package.xml | sysdeps
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e '.[ros,test]'
	touch $@

# The main job: replay -> estimator (shipped Panda weights) -> live evaluation, as a real ROS 2 graph.
demo: install
	$(VENV)/bin/holo-pose-demo --model panda --frames 12 --out $(DEMO)

test: install
	$(PY) -m pytest -q --durations=20 test

clean:
	rm -rf $(VENV) out build *.egg-info
