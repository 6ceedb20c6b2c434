"""What PFM's features can reward: class and azimuth read-outs of the frozen encoder, 512-d against the
authors' random 10-d projection.

PFM (Eq. 20) can only reward a correct pose if the features it matches change with the azimuth. This
encodes the chips of a dataset's ``extended`` split with the SimCLR encoder that PFM uses and runs the
four Table I probes (linear class probe, MLP azimuth probe, 1-NN class and azimuth) on the pooled 512-d
features and on the frozen random 512 -> 10 projection that ``--pfm_projection_dim 10`` applies (the
authors' form), for several projection seeds. JSON on stdout and in ``--out``:

    python benchmarks/pfm_features.py --data RUN/data --encoder RUN/simclr/encoder --out features.json
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
from sar_zero123.evaluation.probes import FeatureSet, extract_features  # noqa: E402
from sar_zero123.training.pfm import random_feature_projection  # noqa: E402
from sar_zero123.training.probes import run_probes  # noqa: E402


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="dataset folder with index.csv")
    parser.add_argument("--encoder", required=True, help="SAREncoder folder (train/pretrain_simclr.py)")
    parser.add_argument("--projection_dim", type=int, default=10)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--epochs", type=int, default=100, help="epochs of the two trained probes")
    parser.add_argument("--out", type=Path, default=None)
    return parser.parse_args(argv)


def projected(features: FeatureSet, weight: torch.Tensor) -> FeatureSet:
    return FeatureSet(features.features @ weight.T, features.labels, features.azimuth_deg)


def main(argv=None) -> dict:
    args = parse_args(argv)
    start = time.perf_counter()
    encoder = SAREncoder.from_pretrained(args.encoder).eval()
    splits = split_records(load_index(args.data), "extended")
    size = encoder.config.image_size
    train, test = (extract_features(encoder, ChipDataset(splits[name], size=size))
                   for name in ("train", "test"))  # fmt: skip
    rows = [{"features": f"{train.features.shape[1]}-d", "seed": None,
             **run_probes(train, test, epochs=args.epochs, generator=torch.Generator().manual_seed(0))}]
    print(json.dumps(rows[-1]), flush=True)
    for seed in args.seeds:
        weight = random_feature_projection(train.features.shape[1], args.projection_dim, seed=seed)
        probes = run_probes(projected(train, weight), projected(test, weight), epochs=args.epochs,
                            generator=torch.Generator().manual_seed(0))  # fmt: skip
        rows.append({"features": f"projected {args.projection_dim}-d", "seed": seed, **probes})
        print(json.dumps(rows[-1]), flush=True)
    result = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
              "n_train": len(splits["train"]), "n_test": len(splits["test"]),
              "seconds": time.perf_counter() - start, "rows": rows}  # fmt: skip
    if args.out is not None:
        write_json_atomic(result, args.out)
    return result


if __name__ == "__main__":
    main()
