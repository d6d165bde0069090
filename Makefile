# Two commands on a fresh machine: `make demo` and `make test`. Both set the machine up first
# (.ci/setup: LLVM for Dr.Jit, .venv, the package) and skip that when it is already done.
PY    := .venv/bin/python
STAMP := .venv/.mi_amr-setup

.PHONY: setup demo test docs bench data clean

setup: $(STAMP)

$(STAMP): pyproject.toml .ci/setup
	bash .ci/setup
	touch $(STAMP)

demo: setup
	$(PY) -m mi_amr demo

test: setup
	$(PY) -m pytest -q

# The documentation site, into docs/_build/html; a Sphinx warning fails the build (make test
# builds it too, in tests/test_docs.py).
docs: setup
	$(PY) -m sphinx -W --keep-going -q -b html docs docs/_build/html

bench: setup
	$(PY) -m mi_amr bench

clean:
	rm -rf out .pytest_cache docs/_build
