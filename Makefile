# Two commands on a fresh machine:  `make demo` (runtime only)  and  `make test` (the development stack).
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python

# tofcore must also run on Python 3.13 with NumPy 2 (Blender 5.1+): a second venv checks that.
PYTHON313 ?= $(firstword $(wildcard $(HOME)/.pyenv/versions/3.13*/bin/python3.13) $(shell command -v python3.13 2>/dev/null))
VENV313   ?= .venv313

.PHONY: demo test test-numpy2 bench venv clean addon docs

# OpenCV comes as opencv-contrib-python-headless (cv2 with cv2.ximgproc). The plain builds (opencv-python-headless,
# which an older venv has, or opencv-python) own the same cv2 folder: installed beside the contrib build, or
# removed after it, they break cv2. Where one is present, both go, and the contrib build is installed anew.
OPENCV_OTHERS := opencv-python-headless opencv-python opencv-contrib-python
pip_names = $$($(1) -m pip show $(2) 2>/dev/null | sed -n 's/^Name: //p' | paste -sd ' ' -)
drop_other_opencv = others="$(call pip_names,$(1),$(OPENCV_OTHERS))"; if [ -n "$$others" ]; then \
	echo "$(1): replacing $$others by opencv-contrib-python-headless (one cv2)"; \
	$(1) -m pip uninstall --quiet --yes $$others $(call pip_names,$(1),opencv-contrib-python-headless); fi

$(VENV)/.installed: requirements-dev.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	@$(call drop_other_opencv,$(PY))
	$(PY) -m pip install --quiet -r requirements-dev.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $@

venv: $(VENV)/.installed

# The demo needs the runtime only (NumPy, tqdm) and numba for the compiled tracer (the same frame as NumPy's in
# 0.38x the time on 2 cores; it compiles once, about 15 s): no bpy, Dask or pytest. A venv that `make test` made
# already has them; pip then installs nothing. The render stops at a real Kinect's 2 mm of depth noise (about 44
# spp, under 60 s on 2 cores), or at 64 spp.
$(VENV)/.runtime: pyproject.toml
	[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[compiled]"
	touch $@

demo: $(VENV)/.runtime
	$(PY) -m tofcore render --scene room --preset kinect_v2 --spp 64 --target-error 2mm --no-noise --out out/demo --verbose

test: venv
	$(PY) -m pytest -q -m "not slow"

test-numpy2:
	@if [ -z "$(PYTHON313)" ]; then echo "python3.13 not found: NumPy 2 check skipped"; else \
	  [ -x $(VENV313)/bin/python ] || $(PYTHON313) -m venv $(VENV313); \
	  $(call drop_other_opencv,$(VENV313)/bin/python); \
	  $(VENV313)/bin/python -m pip install --quiet "numpy>=2" pytest tqdm opencv-contrib-python-headless "OpenEXR>=3.3" trimesh && \
	  $(VENV313)/bin/python -m pip install --quiet --no-deps -e . && \
	  $(VENV313)/bin/python -m pytest -q -m "not slow" tests; fi

bench: venv
	$(PY) bench/bench_transport.py

# The Blender extension: one validated zip for every platform in dist/ (the pure tofcore wheel, no NumPy).
addon: venv
	$(PY) addon/build.py --out dist/

# The add-on in a real Blender GUI (Debian 13's Blender 4.3.2 on a virtual display; root; the first run builds
# /opt/blender-trixie from Debian's mirror, ~3 min): tests/blender_gui/run.py. DOCS=docs/images refreshes the
# README's screenshots.
.PHONY: test-blender
test-blender: addon
	$(PY) tests/blender_gui/run.py dist/tof_camera-$$(sed -n 's/^version = "\(.*\)"/\1/p' blender_manifest.toml).zip \
		--out out/blender-gui $(if $(DOCS),--docs $(DOCS))

# The compiled tracer (numba) in that Blender: the add-on's Install numba from WHEELS (a folder with the cp313
# numba, llvmlite and pip wheels: README, "Tested in a real Blender GUI"), cold/warm/NumPy renders, the textured
# scene under an HDRI World compiled and NumPy; ~5 min.
.PHONY: test-blender-numba
test-blender-numba: addon
	$(PY) tests/blender_gui/numba_run.py dist/tof_camera-$$(sed -n 's/^version = "\(.*\)"/\1/p' blender_manifest.toml).zip \
		--wheels $(or $(WHEELS),$(error WHEELS=folder of the numba, llvmlite and pip wheels)) --out out/blender-numba

# The six thesis experiments (docs/validation.md): PNG plots + JSON numbers in out/studies/, ~10 min on 2 cores.
STUDIES := corner_path_length corner_roughness systematic_error box_wall_error_map flying_pixels led_shadow
.PHONY: studies

$(VENV)/.studies: $(VENV)/.installed pyproject.toml
	$(PY) -m pip install --quiet -e ".[studies]" "numpy>=1.26,<2"
	touch $@

studies: $(VENV)/.studies
	@for s in $(STUDIES); do echo "== studies/$$s.py"; $(PY) studies/$$s.py --out out/studies || exit 1; done

# The documentation site (MkDocs, docs/ + the API reference from the docstrings) into out/site, --strict: a
# link to a missing page, anchor or repository file fails the build. Its own venv with pinned packages.
VENV_DOCS ?= .venv-docs

$(VENV_DOCS)/.installed: docs/requirements.txt
	$(PYTHON) -m venv $(VENV_DOCS)
	$(VENV_DOCS)/bin/python -m pip install --quiet -r docs/requirements.txt
	touch $@

docs: $(VENV_DOCS)/.installed
	NO_MKDOCS_2_WARNING=1 $(VENV_DOCS)/bin/mkdocs build --strict --clean

clean:
	rm -rf $(VENV) $(VENV313) $(VENV_DOCS) out

# Peers (Mitsuba 3, mitransient, Blender Cycles) in a separate venv: studies/crosscheck/README.md.
VENV_BENCH ?= .venv-bench
LIBLLVM19  ?= $(firstword $(wildcard /usr/lib/x86_64-linux-gnu/libLLVM.so.19*))
.PHONY: bench-peers crosscheck

$(VENV_BENCH)/.installed: pyproject.toml
	@[ -n "$(LIBLLVM19)" ] || { echo "libLLVM 19 not found: apt-get update && apt-get install -y libllvm19"; exit 1; }
	$(PYTHON) -m venv $(VENV_BENCH)
	$(VENV_BENCH)/bin/python -m pip install --quiet --upgrade pip
	$(VENV_BENCH)/bin/python -m pip install --quiet -e ".[bench,compiled]"
	touch $@

bench-peers: venv $(VENV_BENCH)/.installed
	DRJIT_LIBLLVM_PATH=$(LIBLLVM19) $(VENV_BENCH)/bin/python bench/bench_peers.py --json out/bench_peers.json

crosscheck: $(VENV_BENCH)/.installed
	DRJIT_LIBLLVM_PATH=$(LIBLLVM19) $(VENV_BENCH)/bin/python studies/crosscheck/crosscheck.py
	DRJIT_LIBLLVM_PATH=$(LIBLLVM19) $(VENV_BENCH)/bin/python studies/crosscheck/error_vs_time.py
