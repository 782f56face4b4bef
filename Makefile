# fullview — make targets (see README). Python and dependencies live in .venv.
PYTHON_SYS ?= python3
VENV       := .venv
PY         := $(VENV)/bin/python
# CONFIG: a pipeline.yaml passed as -c (replaces the workspace's recorded settings); empty: the recorded settings,
# else the code's defaults (the repo's pipeline.yaml is a copy of them).
CONFIG     ?=
CONFIG_ARG := $(if $(CONFIG),-c $(CONFIG))
WORKSPACE  ?= workspace
SYNTH      := $(WORKSPACE)/datasets/synth6
DATASET    ?=
STAGE      ?=

.PHONY: setup run stage status test bench clean eval synth export chromium view

$(VENV)/.installed: pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0; then \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  (apt-get install -y libusb-1.0-0 || (apt-get update && apt-get install -y libusb-1.0-0)) >/dev/null; \
	fi
	$(PYTHON_SYS) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	@touch $@

# The viewer's JavaScript libraries, pinned by package-lock.json and vendored here (the page loads nothing else),
# and Debian's chromium for the browser tests.
VENDOR := viewer/web/node_modules
$(VENDOR)/.installed: viewer/web/package-lock.json
	cd viewer/web && npm ci --no-audit --no-fund --loglevel=error
	@touch $@

chromium:
	@if ! command -v chromium >/dev/null 2>&1; then \
	  echo "installing chromium (browser tests of the viewer)"; \
	  (apt-get install -y chromium || (apt-get update && apt-get install -y chromium)) >/dev/null; \
	fi

setup: $(VENV)/.installed $(VENDOR)/.installed chromium
	@echo "fullview is installed: $(abspath $(VENV))/bin/fullview (or \`source $(VENV)/bin/activate\` for plain \`fullview\`)"

$(SYNTH)/images: | $(VENV)/.installed
	$(PY) -m fullview synth $(SYNTH) --views 6 --width 2048 --seed 0

# With no DATASET: render the default synthetic scene once, reconstruct it, print the eval metrics.
run: setup
ifeq ($(DATASET),)
	@$(MAKE) --no-print-directory $(SYNTH)/images
	$(PY) -m fullview run $(SYNTH) $(CONFIG_ARG) -w $(WORKSPACE)
	$(PY) -m fullview eval $(SYNTH) $(CONFIG_ARG) -w $(WORKSPACE)
	@echo "report: $$($(PY) -m fullview report $(SYNTH) $(CONFIG_ARG) -w $(WORKSPACE))"
else
	$(PY) -m fullview run $(DATASET) $(CONFIG_ARG) -w $(WORKSPACE)
	@echo "report: $$($(PY) -m fullview report $(DATASET) $(CONFIG_ARG) -w $(WORKSPACE))"
endif

stage: setup
	@test -n "$(STAGE)" || (echo "usage: make stage STAGE=<name> DATASET=<path>"; exit 2)
	$(PY) -m fullview run $(or $(DATASET),$(SYNTH)) $(CONFIG_ARG) -w $(WORKSPACE) --only $(STAGE)

status: setup
	$(PY) -m fullview status $(or $(DATASET),$(SYNTH)) $(CONFIG_ARG) -w $(WORKSPACE)

# The viewer on 127.0.0.1 (prints its address): make view [DATASET=…]
view: setup
	$(PY) -m fullview view $(or $(DATASET),$(SYNTH)) $(CONFIG_ARG) -w $(WORKSPACE)

eval: setup
	$(PY) -m fullview eval $(or $(DATASET),$(SYNTH)) $(CONFIG_ARG) -w $(WORKSPACE)

# The current model for other tools: make export FORMAT=colmap|colmap-bin|nerfstudio|ply [DATASET=…]
FORMAT ?= colmap
export: setup
	$(PY) -m fullview export $(or $(DATASET),$(SYNTH)) $(CONFIG_ARG) -w $(WORKSPACE) --format $(FORMAT)

test: setup
	$(PY) -m pytest tests

bench: setup
	$(PY) benchmarks/bench.py $(BENCH_ARGS)

clean:
	rm -rf $(WORKSPACE)

# COLMAP as baseline and reference (README, "COLMAP as baseline and reference").
RENDER_TYPE ?= spherical
.PHONY: colmap-check compare-colmap

# Our SIFT stage against COLMAP's SIFT on the same cube faces: workspace/<dataset>/colmap_check/check.{json,md}.
colmap-check: setup
ifeq ($(DATASET),)
	@$(MAKE) --no-print-directory $(SYNTH)/images
endif
	$(PY) -m fullview colmap-check $(or $(DATASET),$(SYNTH)) $(CONFIG_ARG) -w $(WORKSPACE)

# Our reconstruction against pycolmap.panorama.reconstruct; exits non-zero when benchmarks/baseline.json's
# tolerances are exceeded for this dataset. Results: workspace/<dataset>/compare/.
compare-colmap: setup
ifeq ($(DATASET),)
	@$(MAKE) --no-print-directory $(SYNTH)/images
endif
	$(PY) -m fullview compare $(or $(DATASET),$(SYNTH)) $(CONFIG_ARG) -w $(WORKSPACE) --render-type $(RENDER_TYPE)
