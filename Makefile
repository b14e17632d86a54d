# Two commands on a fresh machine: `make demo` and `make test`.
# Both create .venv if missing and install what they need; a second run reinstalls nothing.
PY      ?= python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.swarmsplat-installed
SUDO    := $(shell [ "$$(id -u)" = "0" ] || echo sudo)

.PHONY: setup demo test bench clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml
	@# open3d links against libusb-1.0; install the system package when it is absent.
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		$(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@[ -x $(VPY) ] || $(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	@# The CPU build of torch first: any other request may pull a multi-GB CUDA build.
	$(VPY) -m pip install -q torch==2.13.0
	$(VPY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/swarmsplat demo --out runs/demo

test: setup
	$(VPY) -m pytest -q

bench: setup
	$(VPY) -m perf all --quick --json perf/results/quick.json

clean-venv:
	rm -rf $(VENV)
