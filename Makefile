# Two commands on a fresh machine:  `make demo`  and  `make test`.
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python

# tofcore must also run on Python 3.13 with NumPy 2 (Blender 5.1+): a second venv checks that.
PYTHON313 ?= $(firstword $(wildcard $(HOME)/.pyenv/versions/3.13*/bin/python3.13) $(shell command -v python3.13 2>/dev/null))
VENV313   ?= .venv313

.PHONY: demo test test-numpy2 bench venv clean addon

$(VENV)/.installed: requirements-dev.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements-dev.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $@

venv: $(VENV)/.installed

demo: venv
	$(PY) -m tofcore render --scene room --preset kinect_v2 --spp 32 --out out/demo --verbose

test: venv
	$(PY) -m pytest -q -m "not slow"

test-numpy2:
	@if [ -z "$(PYTHON313)" ]; then echo "python3.13 not found: NumPy 2 check skipped"; else \
	  [ -x $(VENV313)/bin/python ] || $(PYTHON313) -m venv $(VENV313); \
	  $(VENV313)/bin/python -m pip install --quiet "numpy>=2" pytest opencv-python-headless "OpenEXR>=3.3" && \
	  $(VENV313)/bin/python -m pip install --quiet --no-deps -e . && \
	  $(VENV313)/bin/python -m pytest -q -m "not slow" tests; fi

bench: venv
	$(PY) bench/bench_transport.py

# The Blender extension: one validated zip per platform in dist/ (tofcore + OpenEXR wheels, no NumPy).
addon: venv
	$(PY) addon/build.py --out dist/

clean:
	rm -rf $(VENV) $(VENV313) out
