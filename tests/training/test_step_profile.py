"""``sar_zero123.training.step_profile``: a prior step launches as many operators at any batch."""

from __future__ import annotations

from sar_zero123.pretrained import SIM_PRIOR_ROTATED, resolve_pretrained
from sar_zero123.training.step_profile import count_operators, prior_training_step


def test_a_step_launches_as_many_operators_at_any_batch() -> None:
    counts = []
    for batch in (2, 5):
        forward_backward, optimizer_step, _ = prior_training_step(
            resolve_pretrained(SIM_PRIOR_ROTATED), batch_size=batch
        )
        forward_backward()  # the warm-up, as the benchmark's
        optimizer_step()
        counts.append(
            {
                "forward_backward": count_operators(forward_backward),
                "optimizer": count_operators(optimizer_step),
            }
        )
    small, large = counts
    assert small["optimizer"] == large["optimizer"]
    # the bundled prior's thousands at any batch (a data-dependent branch, such as which samples drop their
    # condition, may add or skip an operator)
    assert (
        small["forward_backward"] > 1000 and abs(small["forward_backward"] - large["forward_backward"]) <= 10
    )
