"""The README's examples run as written (issue 38: docs that are true)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_the_python_example_runs_and_gives_a_view_in_the_normalised_db_domain():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) == 1
    namespace: dict = {}
    exec(compile(blocks[0], str(README), "exec"), namespace)  # noqa: S102 - the README's own example
    view = namespace["view"]
    assert view.shape == (64, 64, 1) and np.isfinite(view).all()
    assert 0.0 <= view.min() and view.max() <= 1.0
    assert namespace["scaling"].denormalize(view).shape == (64, 64, 1)


def test_every_command_in_the_readme_bash_blocks_exists():
    from sar_zero123.cli import COMMANDS

    scripts = {command.script for command in COMMANDS}
    for block in re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S):
        for line in block.splitlines():
            words = line.split()
            if words and words[0].startswith("sar-zero123-"):
                assert words[0] in scripts, line
