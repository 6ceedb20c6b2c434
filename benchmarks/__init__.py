"""Benchmarks and one-off measurements, each runnable as `python benchmarks/<name>.py`; tests import them
as `benchmarks.<name>` (the repository root is on pytest's `pythonpath`)."""
