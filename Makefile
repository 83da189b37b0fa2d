# The two commands a new user needs: `make demo` and `make test`. Both set up first (idempotent).
.PHONY: setup demo test bench bench-pipeline validate-crosstalk clean

setup:
	@bash scripts/setup.sh

demo: setup
	.venv/bin/nrhdr demo --force

test: setup
	.venv/bin/python -m pytest -q -ra --durations=25 tests

bench: setup
	.venv/bin/python benchmarks/reconstruction.py

validate-crosstalk: setup
	.venv/bin/python benchmarks/crosstalk_validation.py

bench-pipeline: setup
	.venv/bin/python benchmarks/pipeline.py

clean:
	rm -rf demo_out .pytest_cache
