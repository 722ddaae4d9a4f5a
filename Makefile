# One-command set-up: `make demo` and `make test` create the environment themselves.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# `synth --render pbr`'s Blender (bpy: Python 3.11, numpy < 2) in an environment of its own,
# found by the library as .venv-pbr (or wherever ANNOTATOR_BPY_PYTHON points).
PYTHON311 ?= python3.11
PBR_VENV  := .venv-pbr
PBR_STAMP := $(PBR_VENV)/.installed

.PHONY: demo test test-fast lint format bench system-deps clean pbr-env

# System libraries: open3d needs libusb at import time; the browser tests need Chromium.
system-deps:
	@if ! ldconfig -p | grep -q libusb-1.0.so.0 || ! command -v chromium >/dev/null; then \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq libusb-1.0-0 libgl1 libgomp1 chromium >/dev/null; \
	fi

$(STAMP): pyproject.toml
	$(MAKE) system-deps
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev,ray]'
	touch $(STAMP)

$(PBR_STAMP):
	$(PYTHON311) -m venv $(PBR_VENV)
	$(PBR_VENV)/bin/pip install -q --upgrade pip
	$(PBR_VENV)/bin/pip install -q bpy==5.0.1
	touch $(PBR_STAMP)

pbr-env: $(PBR_STAMP)

# The main job on a copy of sample_scenes/ (the committed files stay untouched).
demo: $(STAMP)
	rm -rf out/demo && mkdir -p out && cp -r sample_scenes out/demo && rm -f out/demo/scenes/*/annotation.json
	$(BIN)/annotator check out/demo
	$(BIN)/annotator annotate out/demo --workers 2
	$(BIN)/annotator evaluate out/demo --plot out/demo_precision_recall.png --overwrite
	$(BIN)/annotator export out/demo out/demo_bop --format bop --include-pending --overwrite
	@echo "Next: $(BIN)/annotator review out/demo   (then open the printed address)"

# Every test: two workers, a test file to each at a time (its fixtures made once); then the
# browser tests, one at a time (their timings want a quiet machine). The pbr tests render
# with Cycles in .venv-pbr.
test: $(STAMP) $(PBR_STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy annotator viewer
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not browser"
	$(BIN)/python -m pytest -q -m browser

# The inner loop: everything but the tests marked slow (Ray, calibration, browsers, real
# processes and servers, rendered scenes and BOP exports), on every core: under a minute.
test-fast: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -m "not slow" -n auto

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check . && $(BIN)/mypy annotator viewer

format: $(STAMP)
	$(BIN)/ruff format . && $(BIN)/ruff check --fix .

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python -m benchmarks.$$(basename $$b .py) || exit 1; done

clean:
	rm -rf $(VENV) $(PBR_VENV) build *.egg-info
