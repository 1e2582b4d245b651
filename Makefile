# The README's two commands: `make demo` and `make test`. Both set up first (idempotent).
.PHONY: setup demo test lint format bench

setup:
	@bash scripts/setup.sh

demo: setup
	@bash scripts/demo.sh

test: setup
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .
	.venv/bin/python -m pytest -q

lint: setup
	.venv/bin/ruff check --fix .
	.venv/bin/ruff format .
