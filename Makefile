# Two commands on a fresh machine: `make demo` and `make test`.
# Both create .venv if missing and install what they need; a second run reinstalls nothing.
PY      ?= python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.swarmsplat-installed
SUDO    := $(shell [ "$$(id -u)" = "0" ] || echo sudo)

.PHONY: setup browser demo test bench fuzz device-check clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml
	@# open3d links against libusb-1.0; install the system package when it is absent.
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		$(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@# Taichi's Vulkan device (tests on taichi-vulkan, --device vulkan): the Vulkan loader and Mesa's drivers
	@# (lavapipe, a software Vulkan device, where there is no GPU); install them when absent.
	@if ! ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1' || ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1; then \
		echo "installing libvulkan1 and mesa-vulkan-drivers (Taichi on Vulkan)"; \
		$(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libvulkan1 mesa-vulkan-drivers >/dev/null; \
	fi
	@[ -x $(VPY) ] || $(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	@# The CPU build of torch first: any other request may pull a multi-GB CUDA build.
	$(VPY) -m pip install -q torch==2.13.0
	$(VPY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/swarmsplat demo --out runs/demo

# The browser test (`swarmsplat view --screenshot`, tests/test_view_screenshot.py) needs a Chromium: Debian's
# package, installed when no Chromium is on PATH (test only; the demo does not need it).
browser:
	@if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1 \
		&& ! command -v google-chrome >/dev/null 2>&1 && [ -z "$$SWARMSPLAT_CHROMIUM" ]; then \
		echo "installing chromium (browser test)"; \
		$(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq chromium >/dev/null; \
	fi

test: setup browser
	$(VENV)/bin/ruff check
	$(VPY) -m pytest -q

bench: setup
	$(VPY) -m perf all --quick --json runs/bench-quick.json --md runs/bench-quick.md

# Coverage-guided fuzzing of every parser of outside data, FUZZ_SECONDS each (crashes land in tests/fuzz/crashes/,
# which the suite replays).
FUZZ_SECONDS ?= 600
fuzz: setup
	$(VPY) -m pip install -q 'atheris>=2.3'
	$(VPY) -m perf fuzz --seconds $(FUZZ_SECONDS) --json runs/fuzz.json --md runs/fuzz.md

# On a GPU machine (e.g. a Jetson): the suite's cases for DEVICE and a quick benchmark of every perf subject on
# it, into perf/results/device-check-$(DEVICE).json. DEVICE=vulkan checks Taichi's Vulkan device instead.
DEVICE ?= cuda
device-check: setup
	$(VPY) -m perf device-check --device $(DEVICE)

clean-venv:
	rm -rf $(VENV)
