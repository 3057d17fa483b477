# The two commands a newcomer needs: `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: install demo test bench lint clean
install:
	./scripts/install.sh

demo: install
	$(VENV)/bin/kmvipe demo --out out/demo

# In-process tests on both cores; the end-to-end ones (marker slow: real pipelines of five processes, each
# using both cores) one at a time, so that none of them shares the CPU with another pipeline.
test: install
	$(PY) -m pytest -q -n 2 -m "not slow"; fast=$$?; $(PY) -m pytest -q -m slow; slow=$$?; \
	exit $$(( fast || slow ))

bench: install
	$(PY) bench/bus.py

clean:
	rm -rf $(VENV) out .pytest_cache
