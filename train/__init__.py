"""The thin scripts over the stages, importable as `train.<name>` (`from train import finetune_pfm`).

Each script but `plot_augmentations.py` (figures) parses its flags into a stage's typed config and calls the
stage function of `sar_zero123.stages` (`finetune_pfm.py` -> `run_finetune`, `quickstart.py` ->
`run_quickstart`, ...); the stages hold the work, so no script imports another. Each runs as a file, as
the README says (`python train/quickstart.py ...`, `accelerate launch train/finetune_pfm.py ...`); tests
import them as modules of this package, with the repository root on `sys.path` (pytest's `pythonpath` in
`pyproject.toml`). The library and `benchmarks/` never import `train`.
"""
