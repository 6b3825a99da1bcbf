# The loops people run; each target is the same script the README and CI use.
.PHONY: demo test check

demo:
	bin/demo

test:
	bin/test

check:
	.venv/bin/ruff check . && .venv/bin/ruff format --check . && .venv/bin/mypy agents
