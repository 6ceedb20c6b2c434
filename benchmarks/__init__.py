"""Benchmarks and one-off measurements, each runnable as `python benchmarks/<name>.py` (sharing `_common`);
what they measure is library code, tested where it lives. The GPU session scripts (`gpu_prior`,
`gpu_mstar_pfm`) are still imported by their tests as `benchmarks.<name>`."""
