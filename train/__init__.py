"""The training and evaluation scripts, importable as `train.<name>` (`from train import finetune_pfm`).

Each script is a thin `main(argv=None)` over a config dataclass and runs as a file, exactly as the
README says (`python train/quickstart.py ...`, `accelerate launch train/finetune_pfm.py ...`). Tests,
benchmarks and the scripts that drive other scripts (`quickstart.py`, `table1.py`) import them as
modules of this package, with the repository root on `sys.path`: pytest adds it (`pythonpath` in
`pyproject.toml`); a script run as a file that imports a sibling adds it itself, in one guarded line
before its `from train import ...` (Python puts only `train/` on the path for `python train/x.py`).
Nothing loads a script by its file path.
"""
