"""Benchmarks of the IoUV platform and agents (``python -m benchmarks.<name>``)."""
