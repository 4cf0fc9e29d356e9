"""Benchmarks: speed and accuracy together.  Run ``python -m benchmarks [NAME ...]``."""
