# The README's two commands: `make demo` and `make test`. Both set up first (idempotent).
.PHONY: setup demo test lint format bench results

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

# benchmarks/RESULTS.md from benchmarks/results/*.json (after re-running a benchmark)
results: setup
	.venv/bin/python benchmarks/results_md.py
