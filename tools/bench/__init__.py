"""Benchmarks and surveys: run from a checkout (``python -m ballbar.tools.bench.NAME``); not in the wheel."""
