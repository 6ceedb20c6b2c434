"""Progress bars: a live bar on a terminal, whole lines in a log."""

from __future__ import annotations

import io

from sar_zero123.progress import progress_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_gets_whole_lines_and_a_terminal_gets_the_bar():
    log = io.StringIO()
    for _ in progress_bar(range(5), desc="steps", file=log, mininterval=0, miniters=1):
        pass
    text = log.getvalue()
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert len(lines) >= 2 and lines[-1].startswith("steps: 100%") and "5/5" in lines[-1]
    terminal = Terminal()
    for _ in progress_bar(range(5), desc="steps", file=terminal, mininterval=0, miniters=1):
        pass
    assert "\r" in terminal.getvalue()  # redrawn in place


def test_a_closed_bar_that_does_not_stay_leaves_no_blank_lines():
    log = io.StringIO()
    with progress_bar(total=3, desc="epoch", file=log, leave=False, mininterval=0) as bar:
        bar.update(3)
    assert all(line.strip() for line in log.getvalue().splitlines())


def test_a_postfix_set_every_step_does_not_force_a_line_in_a_log():
    log = io.StringIO()
    with progress_bar(total=50, desc="steps", file=log, mininterval=3600) as bar:
        for step in range(50):
            bar.set_postfix(loss=f"{step:.4f}")
            bar.update(1)
    lines = log.getvalue().splitlines()
    assert len(lines) == 2 and "50/50" in lines[-1] and "loss=49.0000" in lines[-1]  # the start and the end
