# gonio: two commands on a fresh Debian machine.
#   make demo   full loop on the simulated instrument (capture, export, fit, render, report)
#   make test   the test suite
# Each installs what it needs: a virtual environment with gonio and its dependencies, and
# Debian's libllvm19 (Mitsuba's fast LLVM variants) when apt-get is available.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.stamp-install

.PHONY: demo test test-fast install llvm chromium clean

demo: $(STAMP)
	$(VENV)/bin/gonio demo

test: $(STAMP) chromium
	$(PY) -m pytest -q

test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

install: $(STAMP)

$(STAMP): pyproject.toml
	@$(MAKE) --no-print-directory llvm
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	@touch $@

# Install a Debian package when missing, as root with apt-get; otherwise say what follows.
# $(1): command that succeeds when it is there; $(2): package; $(3): why; $(4): what happens without it
define apt_install
	@if $(1) >/dev/null 2>&1; then :; \
	elif command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	  echo "installing Debian's $(2) $(3)"; \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(2) >/dev/null 2>&1 || \
	  { apt-get update -q >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(2) >/dev/null 2>&1; } || \
	  echo "gonio: could not install $(2); $(4)"; \
	else echo "gonio: no apt-get as root; $(4) unless $(2) is installed"; fi
endef

# Mitsuba's llvm_ad_* variants need a system libLLVM (Debian's 14/15 make drjit abort; 19 works).
# Without it gonio falls back to scalar_rgb and says so.
llvm:
	$(call apt_install,ls /usr/lib/*/libLLVM*.so.19*,libllvm19,for Mitsuba's LLVM variants,Mitsuba will use scalar_rgb)

# The report test opens the HTML report in headless Chromium; it skips (and says so) without it.
chromium:
	$(call apt_install,command -v chromium,chromium,for the report's browser test,the report's browser test will be skipped)

clean:
	rm -rf $(VENV) gonio-out .pytest_cache
