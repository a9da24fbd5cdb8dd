# magcal — the two commands a new user needs:
#   make demo   calibrate the embedded default (the simulated MPU-9150 — through the real
#               firmware under the AVR emulator when the toolchain is present) end to end
#   make test   run the test suite (every test; make check: the fast tier, the slow ones left out)
# Both create .venv and install what they need (the AVR toolchain via apt-get when run as
# root or with password-less sudo; without it the demo falls back to the pure-Python board).

PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
AVR_PACKAGES := gcc-avr avr-libc binutils-avr arduino-core-avr simavr libsimavr-dev avrdude
# the report's test opens the page in a real browser (headless); the live view's test drives it
# through chromium-driver (Selenium)
BROWSER_PACKAGES := chromium chromium-driver

.PHONY: demo test check bench firmware emulator toolchain systemd-tools clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,i2c,report,logs,fleet]'
	touch $(STAMP)

# Installs the AVR toolchain, simavr and Chromium if they are missing and we may use apt-get.
toolchain:
	@if command -v avr-gcc >/dev/null 2>&1 && [ -f /usr/include/simavr/sim_avr.h ] \
	    && [ -d /usr/share/arduino/hardware/arduino/avr ] && command -v chromium >/dev/null 2>&1 \
	    && command -v chromedriver >/dev/null 2>&1; then \
	  echo "AVR toolchain, simavr and chromium: present"; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing the AVR toolchain and simavr (apt-get)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(AVR_PACKAGES) $(BROWSER_PACKAGES) >/dev/null; \
	elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then \
	  sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(AVR_PACKAGES) $(BROWSER_PACKAGES) >/dev/null; \
	else \
	  echo "note: AVR toolchain or chromium missing and apt-get unavailable; firmware and report-browser" \
	       "tests will be skipped and the demo uses the pure-Python board (install: $(AVR_PACKAGES) $(BROWSER_PACKAGES))"; \
	fi

# systemd-analyze checks the service unit (tests/test_service.py); it needs no running systemd.
systemd-tools:
	@if command -v systemd-analyze >/dev/null 2>&1; then \
	  echo "systemd-analyze: present"; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing systemd (for systemd-analyze)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq systemd >/dev/null; \
	elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then \
	  sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq systemd >/dev/null; \
	else \
	  echo "note: systemd-analyze missing and apt-get unavailable; the service unit test will be skipped"; \
	fi

demo: $(STAMP) toolchain
	@$(BIN)/python -m magcal.cli.demo

# pytest-xdist spreads the tests over the machine's cores (-n auto); loadgroup keeps the tests of
# one xdist_group (an expensive module fixture) on one worker
PYTEST_PARALLEL := -n auto --dist loadgroup

# the whole suite, what CI runs
test: $(STAMP) toolchain systemd-tools
	$(BIN)/python -m pytest -q $(PYTEST_PARALLEL)

# the fast tier: every module still imported and exercised, the tests marked slow left out
check: $(STAMP) toolchain systemd-tools
	$(BIN)/python -m pytest -q $(PYTEST_PARALLEL) -m "not slow"

bench: $(STAMP)
	@for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

firmware:
	$(MAKE) -C firmware

emulator: firmware
	$(MAKE) -C firmware/emulator

clean:
	rm -rf $(VENV) build *.egg-info
	-$(MAKE) -C firmware clean
	-$(MAKE) -C firmware/emulator clean
