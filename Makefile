# gonio: two commands on a fresh Debian machine.
#   make demo   full loop on the simulated instrument, typical errors (calibrate, capture, export, fit, render, report)
#   make test   the test suite
# Each installs what it needs: a virtual environment with gonio and its dependencies at the
# versions pinned in constraints.txt, and Debian's libllvm19 (Mitsuba's fast LLVM variants)
# when apt-get is available. `make test-latest` tries the newest releases instead.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.stamp-install

.PHONY: demo test test-fast test-long test-codegen test-latest lock install llvm chromium udunits clean docs

demo: $(STAMP)
	$(VENV)/bin/gonio demo

# The whole suite on both cores, then the tests whose numbers depend on Dr.Jit's machine
# code once more under another code generation (AVX2 on an AVX-512 host, AVX2 at 4 lanes on an AVX2
# host): the next CI machine may have the other one (issue 12). (A third worker for the waits on
# the simulator and on subprocesses was tried: the main pass took 9:32 against 9:25, its CPU
# time 988 s against 825 s; 2026-12-02, 2-core AVX2 machine.)
test: $(STAMP) chromium udunits
	$(PY) -m pytest -q -n 2 --dist worksteal
	@$(MAKE) --no-print-directory test-codegen

test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

# The tests marked ``long`` (pyproject's addopts leave them out of every other run): the fuzz
# tests with many more examples, the corpora of damaged files in full; the many-seed studies
# also need GONIO_LONG=1.
test-long: $(STAMP)
	GONIO_LONG=1 $(PY) -m pytest -q -n 2 --dist worksteal -m long

test-codegen: $(STAMP)
	@other=$$($(PY) -c "from gonio.models.engine.target import other_target; print(other_target())"); \
	if [ -n "$$other" ]; then \
	  echo "numerical tests again under Dr.Jit's $$other code generation (GONIO_LLVM_TARGET=$$other)"; \
	  GONIO_LLVM_TARGET=$$other $(PY) -m pytest -q -n 2 --dist worksteal -m codegen; \
	else echo "no second code generation on this CPU; numerical tests ran once"; fi

# The suite against the newest releases of every dependency, in a venv of its own.
test-latest:
	$(PYTHON) -m venv .venv-latest
	.venv-latest/bin/python -m pip install -q --upgrade pip
	.venv-latest/bin/python -m pip install -q --upgrade --upgrade-strategy eager -e ".[test]"
	.venv-latest/bin/python -m pytest -q -n 2

# API documentation from the numpydoc docstrings (pdoc, pinned in the test extra) into
# docs/api/ (built, not committed); open docs/api/index.html. The tutorial is docs/tutorial.md.
# docs/build_api.py lists the modules; any pdoc warning fails the build (tests/test_docs_build.py
# builds it the same way in the suite).
docs: $(STAMP)
	$(PY) docs/build_api.py docs/api

# Re-pin constraints.txt to what the current venv holds (after a deliberate upgrade).
lock: $(STAMP)
	$(PY) -m pip freeze --exclude-editable | grep -v '^#' > constraints.txt

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	@$(MAKE) --no-print-directory llvm
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e ".[test]"
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

# NCAS's CF checker (tests/bench/test_dataset_cf.py) reads units through UDUNITS-2; it skips without it.
udunits:
	$(call apt_install,ls /usr/lib/*/libudunits2.so.0*,libudunits2-0,for the CF checker's units,the CF checker test will be skipped)

clean:
	rm -rf $(VENV) .venv-latest gonio-out .pytest_cache
