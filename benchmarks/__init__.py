"""Measurements behind docs/results/, each run as `python benchmarks/<name>.py`; what they measure is library
code, tested where it lives."""
