# VolumeEVM: `make demo` and `make test` set everything up from pinned requirements and run.
# Two environments, one per supported Blender LTS line (the real bpy wheels, never a fake):
#   .venv/py311  bpy 4.5.x, Python 3.11, NumPy 1.26
#   .venv/py313  bpy 5.2.3, Python 3.13, NumPy 2.x
SHELL := /bin/bash
PY311 ?= $(shell command -v python3.11 || echo python3.11)
PY313 ?= $(shell PYENV_VERSION=3.13.0 pyenv which python3.13 2>/dev/null || command -v python3.13 || echo python3.13)
VENVS := .venv/py311 .venv/py313
PYTEST_ARGS ?=

.PHONY: demo demo-data test lint test-py311 test-py313 bench bench-setup debs extension clean

.venv/py311/.stamp: requirements/py311.txt
	rm -rf .venv/py311
	$(PY311) -m venv .venv/py311
	.venv/py311/bin/pip install --quiet --disable-pip-version-check -r requirements/py311.txt
	touch $@

.venv/py313/.stamp: requirements/py313.txt
	rm -rf .venv/py313
	$(PY313) -m venv .venv/py313
	.venv/py313/bin/pip install --quiet --disable-pip-version-check -r requirements/py313.txt
	touch $@

test: lint test-py311 test-py313

# Lint (pyproject.toml: line length, unused names, import order) before the tests: zero findings.
lint: .venv/py313/.stamp
	.venv/py313/bin/ruff check .

test-py311: .venv/py311/.stamp | debs
	.venv/py311/bin/python -m pytest tests $(PYTEST_ARGS)

test-py313: .venv/py313/.stamp | debs
	.venv/py313/bin/python -m pytest tests $(PYTEST_ARGS)

# The demo's CT head: fetched from the Debian archive (pinned package and SHA-256 digests) and
# decoded by sample_blends/fetch_ct_head.py; see sample_blends/data/README.md.
CT_HEAD := sample_blends/data/ct_head_invesalius.npy

$(CT_HEAD): sample_blends/fetch_ct_head.py | .venv/py313/.stamp
	.venv/py313/bin/python sample_blends/fetch_ct_head.py sample_blends/data

demo-data: $(CT_HEAD)

demo: .venv/py313/.stamp $(CT_HEAD)
	.venv/py313/bin/python sample_blends/make_demo.py --out out

# The extension: one zip per platform of the manifest (dist/volumeevm-VERSION-linux_x64.zip...),
# each with the pure wheels and that platform's Numba and llvmlite for Python 3.11 and 3.13 (all
# pinned in the manifest, fetched from PyPI into wheels/ by requirements/fetch_wheels.py), built
# and validated by the bpy wheel's own tool (the code of `blender --command extension build`).
BLENDER_EXT = $(firstword $(wildcard .venv/py313/lib/python3.13/site-packages/bpy/*/scripts/addons_core/bl_pkg/cli/blender_ext.py))
VERSION = $(shell sed -n 's/^version = "\(.*\)"/\1/p' blender_manifest.toml)

extension: .venv/py313/.stamp
	.venv/py313/bin/python requirements/fetch_wheels.py
	mkdir -p dist
	rm -f dist/volumeevm-$(VERSION)*.zip
	.venv/py313/bin/python $(BLENDER_EXT) build --source-dir . --output-dir dist --split-platforms
	for zip in dist/volumeevm-$(VERSION)-*.zip; do .venv/py313/bin/python $(BLENDER_EXT) validate $$zip || exit 1; done
	@ls -l dist/volumeevm-$(VERSION)-*.zip

# Debian packages, installed (apt-get, as root or with sudo) only when missing: the Mesa
# EGL/OpenGL libraries that offscreen GPU drawing needs (the GPU tests, VTK in the benchmarks),
# and VolPack (the benchmarks' peer; the tests read the original brainsmall.den of its examples).
DEBS := libegl1 libegl-mesa0 libgl1-mesa-dri libvolpack1-dev

debs:
	@missing=""; for p in $(DEBS); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q 'ok installed' || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
	  echo "apt-get install$$missing"; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq$$missing; \
	fi

# Bench peers: VTK and matplotlib from requirements/bench.txt into .venv/py313; VolPack and the
# Mesa libraries VTK renders offscreen with from Debian (debs); the VolPack driver
# (bench/peers/volpack_driver.c) compiled against Debian's libvolpack.a.
VOLPACK_DRIVER := bench/peers/build/volpack_driver

.venv/py313/.bench-stamp: .venv/py313/.stamp requirements/bench.txt
	.venv/py313/bin/pip install --quiet --disable-pip-version-check -r requirements/bench.txt
	touch $@

$(VOLPACK_DRIVER): bench/peers/volpack_driver.c | debs
	mkdir -p $(@D)
	gcc -O2 -Wall -o $@ $< -l:libvolpack.a -lm

bench-setup: debs .venv/py313/.bench-stamp $(VOLPACK_DRIVER)

bench: bench-setup
	.venv/py313/bin/python bench/bench_evm.py --out bench/results
	.venv/py313/bin/python bench/bench_dvr.py --out bench/results
	.venv/py313/bin/python bench/bench_stability.py --out bench/results
	.venv/py313/bin/python bench/bench_labels.py --out bench/results
	.venv/py313/bin/python bench/readme_tables.py

clean:
	rm -rf .venv out dist wheels
