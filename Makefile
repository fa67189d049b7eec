# Set-up and checks. `make test` and `make demo` create or refresh .venv themselves.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test demo lint venv bench clean

venv: $(STAMP)

# Reinstall only when the packaging changes; a second run skips this.
$(STAMP): setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check --upgrade 'pip>=23'
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[ros,test]'
	touch $(STAMP)

lint: $(STAMP)
	$(PY) -m flake8 identification_node test bench setup.py

test: lint
	$(PY) -m pytest -q -p no:cacheprovider test

demo: $(STAMP)
	$(PY) -m identification_node structure --robot mit_dd_arm

bench: $(STAMP)
	@for b in bench/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) build install log
