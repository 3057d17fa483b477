# The two commands a newcomer needs: `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: install demo test bench lint clean
install:
	./scripts/install.sh

demo: install
	$(VENV)/bin/kmvipe demo --out out/demo

test: install
	$(PY) -m pytest -q

bench: install
	$(PY) bench/bus.py

clean:
	rm -rf $(VENV) out .pytest_cache
