"""The flags each command lists in ``--help``, and the settings it takes without a flag (issue 62).

    python benchmarks/flag_count.py --out flag_count.json

A flag is an option ``--help`` lists (``--help`` itself not counted); a setting without a flag is a field set
with ``--set FIELD=VALUE`` or a ``--config`` file, listed at the end of ``--help``
(:func:`sar_zero123.config.advanced_fields`). Writes JSON and prints a table.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

from _common import script_parser

from sar_zero123 import cli, config
from sar_zero123.config.json_io import write_json_atomic

#: The settings without a flag of a config class (none on a tree older than them: run with PYTHONPATH=<tree>).
advanced_fields = getattr(config, "advanced_fields", lambda cls: {})


def listed_flags(command: cli.Command) -> list[str]:
    """The options ``<command> --help`` lists, ``--help`` itself left out (each counted once)."""
    text = io.StringIO()
    with contextlib.redirect_stdout(text), contextlib.suppress(SystemExit):
        getattr(cli, command.function)(["--help"])
    flags_part = text.getvalue().partition("settings without a flag")[0]
    found = re.findall(r"^\s+(--[a-z0-9_]+)", flags_part, re.M)
    return sorted(set(found) - {"--help"})


def main() -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--out", default="flag_count.json", help="output JSON")
    args = parser.parse_args()
    rows = {}
    for command in cli.COMMANDS:
        flags = listed_flags(command)
        without = len(advanced_fields(cli.config_class(command)))
        rows[command.script] = {"flags": len(flags), "settings_without_a_flag": without, "listed": flags}
    record = {"total_flags": sum(r["flags"] for r in rows.values()),
              "total_settings_without_a_flag": sum(r["settings_without_a_flag"] for r in rows.values()),
              "commands": rows}  # fmt: skip
    write_json_atomic(record, Path(args.out))
    print("| command | flags | settings without a flag |\n| --- | --- | --- |")
    for script, r in rows.items():
        print(f"| {script} | {r['flags']} | {r['settings_without_a_flag']} |")
    print(f"| all | {record['total_flags']} | {record['total_settings_without_a_flag']} |")
    return record


if __name__ == "__main__":
    main()
