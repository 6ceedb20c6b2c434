"""benchmarks/step_operators.py: the operators of one training step do not grow with the batch."""

from __future__ import annotations

import json

from benchmarks import step_operators


def test_a_step_launches_as_many_operators_at_any_batch_and_writes_its_counts(tmp_path) -> None:
    results = [
        step_operators.main(
            [
                "--batch_size",
                str(batch),
                "--steps",
                "1",
                "--device",
                "cpu",
                "--out",
                str(tmp_path / f"b{batch}.json"),
            ]
        )  # fmt: skip
        for batch in (2, 5)
    ]
    small, large = (result["operators_per_step"] for result in results)
    assert small["optimizer"] == large["optimizer"]
    # the micro UNet's thousands at any batch (a data-dependent branch, such as which samples drop their
    # condition, may add or skip an operator)
    assert (
        small["forward_backward"] > 1000 and abs(small["forward_backward"] - large["forward_backward"]) <= 10
    )
    written = json.loads((tmp_path / "b5.json").read_text())
    assert written["operators_per_step"] == large and written["settings"]["batch_size"] == 5
    assert written["pairs_per_second"] == 5 / written["step_seconds"]
