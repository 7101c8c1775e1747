"""Benchmarks that print JSON figures (never timed tests): ``python -m pipeline.bench NAME``."""
