# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-gpu check-wheel docs notebooks lint bench clean

$(VPY):
	$(PY) -m venv $(VENV)

# CPU torch first (where no torch is present) so that pip does not pull the multi-GB CUDA build.
$(STAMP): $(VPY) pyproject.toml
	$(VPY) -m pip install -q --upgrade pip
	$(VPY) -c "import torch" 2>/dev/null || $(VPY) -m pip install -q torch==2.13.0
	$(VPY) -m pip install -q -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(VPY) -m training.demo --out out

test: $(STAMP)
	$(VPY) -m ruff check torchpf priors training tests benchmarks
	$(VPY) -m pytest -q -n 2

# the tests marked `cuda` (the device fixture's CUDA half among them); they skip where no GPU is present
test-gpu: $(STAMP)
	$(VPY) -m pytest -q -m cuda

# the install-from-wheel check: build the wheel, install it (with OpenCV) into a fresh venv, run the README
# quickstart and the console scripts from an empty folder outside the source tree
WHEEL_DIR := build/wheel-check
check-wheel:
	rm -rf $(WHEEL_DIR) && $(PY) -m venv $(WHEEL_DIR)/venv
	$(WHEEL_DIR)/venv/bin/python -m pip install -q torch==2.13.0
	$(WHEEL_DIR)/venv/bin/python -m pip wheel -q --no-deps -w $(WHEEL_DIR)/dist .
	$(WHEEL_DIR)/venv/bin/python -m pip install -q "$$(ls $(WHEEL_DIR)/dist/torchpf-*.whl)[opencv]"
	run=$$(mktemp -d) && cd $$run && $(CURDIR)/$(WHEEL_DIR)/venv/bin/python $(CURDIR)/.ci/check_wheel.py $(CURDIR)/README.md

# API reference from the docstrings (Sphinx autodoc + napoleon, the `docs` extra), warnings as errors: a docstring
# that does not parse fails. autosummary writes one page per module into docs/_api (regenerated each time).
docs: $(STAMP)
	rm -rf docs/_api build/docs
	$(VPY) -m sphinx -b html -q -W --keep-going docs build/docs
	@echo "API reference: build/docs/index.html"

# re-execute the notebooks and store them with their outputs (figures visible when browsing); the suite
# executes them too (tests/test_notebooks.py) and checks that the stored copies have outputs
notebooks: $(STAMP)
	TORCHPF_WRITE_NOTEBOOKS=1 $(VPY) -m pytest -q -n 0 -p no:cacheprovider tests/test_notebooks.py

lint: $(STAMP)
	$(VPY) -m ruff format torchpf priors training tests benchmarks
	$(VPY) -m ruff check --fix torchpf priors training tests benchmarks

bench: $(STAMP)
	$(VPY) -m benchmarks.fk

clean:
	rm -rf $(VENV) out .pytest_cache build docs/_api
