"""``python -m sar_zero123.augment_dataset``: exit 0 on success; a refusal in one line (``--traceback``:
in full)."""

from functools import partial

from sar_zero123.augment_dataset import main
from sar_zero123.runs.refusals import run_command

if __name__ == "__main__":
    command = partial(main, prog="python -m sar_zero123.augment_dataset")
    raise SystemExit(run_command(command, "sar-zero123-augment"))
