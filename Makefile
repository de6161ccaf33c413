# Two commands for a newcomer: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

export RERUN_ANALYTICS ?= 0

.PHONY: setup demo test test-fast bench screenshot firmware clean

setup: $(STAMP)

$(STAMP): pyproject.toml setup.py $(wildcard fusion/*.c drive/*.c tools/sim/*.c)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[all,dev]"
	touch $(STAMP)

demo: setup
	$(BIN)/fieldlog demo

# The whole suite, slow tests included, on every core (pytest-xdist; the workers share the simulated drives,
# tests/conftest.py); test-fast leaves out the tests marked slow. One worker more than the cores: many tests
# wait on the clock (real-time runs of the daemon, the emulated board, gpsd), and the extra worker computes
# meanwhile.
WORKERS ?= $(shell echo $$(( $$(nproc 2>/dev/null || echo 1) + 1 )))
# pytest exits 5 when it collected no test: that is a failure here too.
define pytest
$(BIN)/python -m pytest -q $(1); rc=$$?; \
if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; fi; exit $$rc
endef

test: setup
	@$(call pytest,-n $(WORKERS) --dist worksteal)

test-fast: setup
	@$(call pytest,-n $(WORKERS) --dist worksteal -m "not slow")

bench: setup
	$(BIN)/python -m fieldlog.tools.dev.bench --markdown

# the DAQ board's firmware images (firmware/README.md); needs `apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi`
firmware:
	$(MAKE) -C firmware

# docs/viewer.png; needs `apt-get install -y xvfb xauth mesa-vulkan-drivers` (not part of `make test`)
screenshot: setup
	$(BIN)/python -m fieldlog.tools.dev.screenshot

clean:
	rm -rf $(VENV) out .pytest_cache .hypothesis firmware/build
