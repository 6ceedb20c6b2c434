"""How many operators one training step of a prior launches, and how long the step takes.

    python benchmarks/step_operators.py --pipeline sar-zero123/sim-prior-rotated --batch_size 64 \\
        --out OUT.json

On a GPU every operator is at least one kernel launch, a few microseconds of host time whatever the batch:
a step that launches thousands of operators is bound by the host when the model is small. The script
counts the ``aten::`` operator calls of one forward and backward and of one optimiser step of a prior's
training step (:func:`sar_zero123.training.step_profile.prior_training_step`, counted by
:func:`~sar_zero123.training.step_profile.count_operators`), then times ``--steps`` whole steps.
``--compile`` times the same step with the UNet compiled (``torch.compile``, inductor), the first step
(the compilation) apart. It writes the counts and times as JSON.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from typing import Any

import torch
from _common import script_parser, synchronize

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.training.step_profile import count_operators, prior_training_step


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = script_parser(__doc__)
    parser.add_argument("--pipeline", default="sar-zero123/sim-prior-rotated", help="bundled name or folder")
    parser.add_argument("--batch_size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=5, help="timed steps after one warm-up step")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--bf16", action="store_true", help="autocast the step to bfloat16 (a GPU run's)")
    parser.add_argument("--compile", default=None, choices=["default", "reduce-overhead", "max-autotune"])
    parser.add_argument("--loop_optimizer", action="store_true",
                        help="torch's default for-loop AdamW instead of the fine-tune's fused one")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON file of the counts and times")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    forward_backward, optimizer_step, _ = prior_training_step(
        resolve_pretrained(args.pipeline), batch_size=args.batch_size, device=args.device, bf16=args.bf16,
        compile_mode=args.compile, loop_optimizer=args.loop_optimizer, seed=args.seed,
    )  # fmt: skip
    start = time.perf_counter()
    forward_backward()  # the warm-up (and, with --compile, the compilation)
    optimizer_step()
    synchronize(args.device)
    first = time.perf_counter() - start
    counts = {"forward_backward": count_operators(forward_backward),
              "optimizer": count_operators(optimizer_step)}
    synchronize(args.device)
    start = time.perf_counter()
    for _ in range(args.steps):
        forward_backward()
        optimizer_step()
    synchronize(args.device)
    seconds = (time.perf_counter() - start) / args.steps
    device = torch.cuda.get_device_name() if torch.device(args.device).type == "cuda" else "cpu"
    result = {
        "settings": vars(args), "device": f"{device}, torch {torch.__version__}",
        "operators_per_step": counts, "first_step_seconds": first, "step_seconds": seconds,
        "steps_per_second": 1.0 / seconds, "pairs_per_second": args.batch_size / seconds,
    }  # fmt: skip
    print(result)
    if args.out:
        write_json_atomic(result, args.out)
    return result


if __name__ == "__main__":
    main()
