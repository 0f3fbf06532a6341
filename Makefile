# Two commands for a fresh machine: `make demo` and `make test`. Both set up .venv first (idempotent).
.PHONY: setup demo test clean

setup:
	@bash scripts/setup.sh

demo: setup
	.venv/bin/nerfbake demo

test: setup
	.venv/bin/python -m pytest -q -p no:cacheprovider tests

clean:
	rm -rf outputs .pytest_cache
