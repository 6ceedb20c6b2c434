"""Can PFM's encoder see the pose of a generated view? Class and azimuth read-outs of generated views.

PFM (Eq. 20) rewards a generated view whose encoder features match the target's. It can reward the right
pose only if the encoder reads the pose of *generated* views, not only of real chips: this generates the
target view of the evaluate stage's pairs (same pairs and seeds as ``train/evaluate.py`` for the same
``--n``, ``--seed`` and protocol) with each pipeline, encodes the views with the SimCLR encoder PFM uses, and
reads class and azimuth from the features with the Table I probes fitted on the real chips of the
``extended`` train split, less the pairs' own chips (1-NN class and azimuth; MLP azimuth probe; linear class
probe). Beside each model,
on the same pairs: the real target views (the ceiling: what the encoder reads from a true view) and the
input copied as output (the floor: the input's azimuth scored against the target's). With
``--projection_dim K`` the same read-outs of the authors' random ``K``-d projection are added.

    python benchmarks/pfm_pose_readout.py --pipeline RUN/finetune_lambda0/pipeline \\
        RUN/finetune_lambda4/pipeline --pipeline_names lambda0 lambda4 --encoder RUN/simclr/encoder \\
        --evaluators RUN/evaluators --data RUN/data --protocol ood-TANK --n 512 --out readout.json

JSON on stdout (a line per row) and in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sar_zero123.config import write_json_atomic  # noqa: E402
from sar_zero123.data import ChipDataset, load_index, split_records  # noqa: E402
from sar_zero123.encoder import SAREncoder  # noqa: E402
from sar_zero123.evaluation.evaluators import load_evaluators  # noqa: E402
from sar_zero123.evaluation.probes import FeatureSet, extract_features  # noqa: E402
from sar_zero123.evaluation.protocol import build_pair_sets, generate_pair_targets  # noqa: E402
from sar_zero123.evaluation.scoring import resize_for_evaluator  # noqa: E402
from sar_zero123.model.pipeline import SARZero123Pipeline  # noqa: E402
from sar_zero123.training.pfm import random_feature_projection  # noqa: E402
from sar_zero123.training.probes import run_probes  # noqa: E402


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pipeline", nargs="+", required=True)
    parser.add_argument("--pipeline_names", nargs="+", required=True)
    parser.add_argument("--encoder", required=True, help="SAREncoder folder (the one PFM used)")
    parser.add_argument("--evaluators", required=True, help="the evaluate stage's evaluators (pairs only)")
    parser.add_argument("--data", required=True, help="dataset folder with index.csv")
    parser.add_argument("--protocol", default="ood-TANK")
    parser.add_argument("--n", type=int, default=512, help="pairs in all (half seen, half unseen with ood-*)")
    parser.add_argument("--num_inference_steps", type=int, default=20)
    parser.add_argument("--guidance_scale", type=float, default=3.0)
    parser.add_argument("--projection_dim", type=int, default=None, help="also the random K-d projection")
    parser.add_argument("--epochs", type=int, default=100, help="epochs of the two trained probes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if len(args.pipeline) != len(args.pipeline_names):
        parser.error(f"--pipeline_names: {len(args.pipeline_names)} names for {len(args.pipeline)} pipelines")
    return args


@torch.no_grad()
def encode(encoder: SAREncoder, images: torch.Tensor, labels, azimuth_deg) -> FeatureSet:
    """Features of normalised-dB images ``(N, 1, S, S)`` at the encoder's size, with their targets."""
    images = resize_for_evaluator(images, encoder.config.image_size)
    features = torch.cat([encoder(batch) for batch in images.split(128)])
    return FeatureSet(features.float(), labels.long(), azimuth_deg.float() % 360.0)


def without_chips(train: FeatureSet, *others: FeatureSet, tol: float = 1e-5) -> FeatureSet:
    """``train`` without the chips whose features equal one of ``others``' (the pairs' own chips).

    With an ``ood-*`` protocol the unseen group draws its pairs from every chip of the held-out class, some of
    them in the ``extended`` train split the probes are fitted on: a 1-NN read-out of such a target would
    find the target itself.
    """
    reference = torch.cat([other.features for other in others])
    nearest = torch.cdist(train.features, reference).min(dim=1).values
    keep = nearest > tol * (1.0 + train.features.norm(dim=1))
    return FeatureSet(train.features[keep], train.labels[keep], train.azimuth_deg[keep])


def readouts(train: FeatureSet, test: FeatureSet, weight: torch.Tensor | None, epochs: int) -> dict:
    """The four Table I probes of ``test`` (fitted on ``train``), optionally after the projection."""
    if weight is not None:
        train = FeatureSet(train.features @ weight.T, train.labels, train.azimuth_deg)
        test = FeatureSet(test.features @ weight.T, test.labels, test.azimuth_deg)
    return run_probes(train, test, epochs=epochs, generator=torch.Generator().manual_seed(0))


def main(argv=None) -> dict:
    args = parse_args(argv)
    start = time.perf_counter()
    device = torch.device("cpu")
    encoder = SAREncoder.from_pretrained(args.encoder).eval()
    records = split_records(load_index(args.data), "extended")["train"]
    train = extract_features(encoder, ChipDataset(records, size=encoder.config.image_size))
    weights = {"features": None}
    if args.projection_dim is not None:
        weights[f"projected {args.projection_dim}-d"] = random_feature_projection(
            train.features.shape[1], args.projection_dim, seed=args.seed
        )
    evaluators = load_evaluators(args.evaluators, device=device)
    first = SARZero123Pipeline.from_pretrained(args.pipeline[0])  # its chip size is the pairs'
    pairs = build_pair_sets(
        evaluators, data=args.data, protocol=args.protocol, n=args.n, seed=args.seed,
        image_size=first.default_image_size, work_dir=args.out.parent, evaluators_name=args.evaluators,
    )  # fmt: skip
    # the floor and the ceiling: the pairs' own chips, encoded once (also to leave them out of the probes)
    chips = {(name, group): encode(encoder, images, pair_set.labels, pair_set.target_azimuth_deg)
             for group, pair_set in pairs.items()
             for name, images in (("input copy (floor)", pair_set.inputs),
                                  ("real target (ceiling)", pair_set.targets))}  # fmt: skip
    excluded = len(train.labels)
    train = without_chips(train, *chips.values())
    excluded -= len(train.labels)
    rows = []

    def add_rows(name: str, group: str, test: FeatureSet) -> None:
        for features, weight in weights.items():
            row = {"model": name, "group": group, "features": features, "n": len(test.labels),
                   **readouts(train, test, weight, args.epochs)}  # fmt: skip
            rows.append(row)
            print(json.dumps(row), flush=True)

    for name in dict.fromkeys(name for name, _ in chips):  # floor, then ceiling; each group in order
        for group in pairs:
            add_rows(name, group, chips[name, group])
    for index, (name, path) in enumerate(zip(args.pipeline_names, args.pipeline, strict=True)):
        pipe = first if index == 0 else SARZero123Pipeline.from_pretrained(path)
        pipe.set_progress_bar_config(disable=True)
        for group, pair_set in pairs.items():
            images, _ = generate_pair_targets(
                pipe, pair_set, num_inference_steps=args.num_inference_steps,
                guidance_scale=args.guidance_scale, batch_size=16, device=device,
            )  # fmt: skip
            add_rows(name, group, encode(encoder, images, pair_set.labels, pair_set.target_azimuth_deg))
    result = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
              "n_train": len(train.labels), "n_excluded": excluded, "seconds": time.perf_counter() - start,
              "rows": rows}  # fmt: skip
    write_json_atomic(result, args.out)
    return result


if __name__ == "__main__":
    main()
