"""Is the VAE the bottleneck? Class and pose kept through each VAE's round trip, with and without speckle.

    python benchmarks/vae_round_trip.py --vae sar-zero123/sim-prior-rotated sar-zero123/sim-prior-proxy \\
        --names rotated proxy --evaluators RUN/evaluators --data DATA --protocol ood-T72 \\
        --n 800 --speckle_looks 1 --out vae_round_trip.json

Scores the target views of the evaluate stage's pairs (the same pairs for the same ``--n``, ``--seed`` and
protocol) encoded (posterior mode) and decoded by each VAE, beside the floor (the input copied) and the
real target, with the evaluate stage's metrics: a latent model can keep no more of the class and pose
than its VAE's round trip does. With ``--speckle_looks`` each round trip is also scored with speckle
re-added (:func:`sar_zero123.augment.readd_speckle`). ``--vae`` takes AutoencoderKL folders, pipeline
folders (their ``vae/``) or bundled pipeline names. Writes JSON (rows, settings, seconds per VAE) and
prints a Markdown table.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from _common import script_parser

from sar_zero123.augment import readd_speckle
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.evaluation.evaluators import load_evaluators
from sar_zero123.evaluation.protocol import INPUT_COPY, REAL_TARGET, build_pair_sets, score
from sar_zero123.evaluation.tables import vae_round_trip_markdown
from sar_zero123.model.vae import load_pretrained_vae, reconstruct_in_batches


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--vae", nargs="+", required=True, help="AutoencoderKL/pipeline folders, names")
    parser.add_argument("--names", nargs="+", required=True, help="one row name per --vae")
    parser.add_argument("--evaluators", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--protocol", default="ood-T72")
    parser.add_argument("--n", type=int, default=800, help="pairs in all (half seen, half unseen with ood-*)")
    parser.add_argument("--image_size", type=int, default=64)
    parser.add_argument("--crop_size", type=int, default=64)
    parser.add_argument("--speckle_looks", type=int, default=None, help="also score with speckle re-added")
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    if len(args.vae) != len(args.names):
        parser.error(f"--names has {len(args.names)} names for {len(args.vae)} VAEs")
    out = Path(args.out)
    evaluators = load_evaluators(args.evaluators)
    pairs = build_pair_sets(
        evaluators, data=args.data, protocol=args.protocol, n=args.n, image_size=args.image_size,
        work_dir=out.parent, seed=args.seed, evaluators_name=args.evaluators,
    )  # fmt: skip
    scoring = {"crop_size": args.crop_size, "paper_scoring_size": 256, "batch_size": args.batch_size,
               "device": torch.device("cpu")}  # fmt: skip
    scaling = evaluators.classifier.scaling
    rows = {
        INPUT_COPY: {group: score(p.inputs, p, evaluators, **scoring) for group, p in pairs.items()},
        REAL_TARGET: {group: score(p.targets, p, evaluators, **scoring) for group, p in pairs.items()},
    }
    seconds = {}
    for name, path in zip(args.names, args.vae):
        vae = load_pretrained_vae(path).eval()
        start = time.perf_counter()
        views = {group: reconstruct_in_batches(vae, p.targets, args.batch_size) for group, p in pairs.items()}
        seconds[name] = time.perf_counter() - start
        rows[name] = {group: score(views[group], p, evaluators, **scoring) for group, p in pairs.items()}
        if args.speckle_looks is not None:
            rows[f"{name} + speckle"] = {}
            for group, p in pairs.items():
                generator = torch.Generator().manual_seed(args.seed)  # the same speckle for every VAE
                speckled = readd_speckle(views[group], scaling.max_db - scaling.min_db, args.speckle_looks,
                                         generator)  # fmt: skip
                rows[f"{name} + speckle"][group] = score(speckled, p, evaluators, **scoring)
        print(f"{name}: {json.dumps(rows[name])}", flush=True)
    write_json_atomic({"settings": vars(args), "rows": rows, "round_trip_seconds": seconds,
                       "pairs": {group: len(p) for group, p in pairs.items()}}, out)  # fmt: skip
    print(vae_round_trip_markdown(rows))


if __name__ == "__main__":
    main()
