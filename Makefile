# Two commands for a newcomer: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

export RERUN_ANALYTICS ?= 0

.PHONY: setup demo test bench screenshot firmware clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[all,dev]"
	touch $(STAMP)

demo: setup
	$(BIN)/fieldlog demo

# pytest exits 5 when it collected no test: that is a failure here too.
test: setup
	@$(BIN)/python -m pytest -q; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; fi; exit $$rc

# every bench's full output on stderr, then its figures as rows of docs/results.md's table on stdout
bench: setup
	$(BIN)/python -m fieldlog.tools.bench --markdown

# the DAQ board's firmware images (firmware/README.md); needs `apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi`
firmware:
	$(MAKE) -C firmware

# docs/viewer.png; needs `apt-get install -y xvfb xauth mesa-vulkan-drivers` (not part of `make test`)
screenshot: setup
	$(BIN)/python -m fieldlog.tools.screenshot

clean:
	rm -rf $(VENV) out .pytest_cache .hypothesis firmware/build
