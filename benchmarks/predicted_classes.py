"""Which class does the evaluator read in generated views? (is an accuracy gain fidelity or a bias?)

    python benchmarks/predicted_classes.py \\
        --pipeline RUN/finetune_lambda0/pipeline RUN/finetune_lambda4/pipeline \\
        --pipeline_names lambda=0 lambda=4 --evaluators RUN/evaluators --data DATA --protocol ood-T72 \\
        --n 128 --out predicted_classes.json

Generates the target view of the evaluate stage's pairs (same pairs and seeds for the same
`--n`, `--seed` and protocol) and counts the classifier's predictions per group. A model whose unseen-class
accuracy rises because it draws every view more like that class shows the same rise on the seen pairs.
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

import torch

from sar_zero123.evaluation.evaluators import load_evaluators
from sar_zero123.evaluation.protocol import build_pair_sets, generate_pair_targets
from sar_zero123.evaluation.scoring import resize_for_evaluator
from sar_zero123.model.pipeline import SARZero123Pipeline


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", nargs="+", required=True)
    parser.add_argument("--pipeline_names", nargs="+", required=True)
    parser.add_argument("--evaluators", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--protocol", default="ood-T72")
    parser.add_argument("--n", type=int, default=128, help="pairs in all (half seen, half unseen with ood-*)")
    parser.add_argument("--num_inference_steps", type=int, default=20)
    parser.add_argument("--guidance_scale", type=float, default=3.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    if len(args.pipeline) != len(args.pipeline_names):
        raise ValueError(f"pipeline_names: {len(args.pipeline_names)} names, {len(args.pipeline)} pipelines")
    device = torch.device("cpu")
    evaluators = load_evaluators(args.evaluators, device=device)
    result: dict = {"protocol": args.protocol, "n": args.n, "models": {}}
    pairs = None
    for name, path in zip(args.pipeline_names, args.pipeline):
        pipe = SARZero123Pipeline.from_pretrained(path)
        pipe.set_progress_bar_config(disable=True)
        if pairs is None:
            pairs = build_pair_sets(
                evaluators, data=args.data, protocol=args.protocol, n=args.n, seed=args.seed,
                image_size=pipe.default_image_size, work_dir=Path(args.out).parent,
                evaluators_name=args.evaluators,
            )  # fmt: skip
        for group, pair_set in pairs.items():
            images, _ = generate_pair_targets(
                pipe, pair_set, num_inference_steps=args.num_inference_steps,
                guidance_scale=args.guidance_scale, batch_size=16, device=device,
            )  # fmt: skip
            with torch.no_grad():
                views = resize_for_evaluator(images, evaluators.image_size)
                predicted = evaluators.classifier(views).argmax(1)
            counts = collections.Counter(evaluators.class_names[i] for i in predicted.tolist())
            result["models"].setdefault(name, {})[group] = {
                "accuracy": (predicted == pair_set.labels).double().mean().item(),
                "n": len(pair_set),
                "predicted": dict(counts.most_common()),
            }
            print(name, group, json.dumps(result["models"][name][group]), flush=True)
    Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
