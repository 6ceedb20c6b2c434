"""Paper-comparable against corrected MS-SSIM and Kuan+SSIM on real MSTAR view pairs (input vs target).

Scores the input view of each pair as if it were the generated target view (the `input copy` baseline of
Table III), so no model is needed. JSON on stdout (and in ``--out``).

    python benchmarks/paper_metrics_mstar.py --data /path/to/mstar --num_pairs 100 --out pairs.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sar_zero123.data import ViewPairDataset, load_index, split_records  # noqa: E402
from sar_zero123.evaluation.metrics import kuan_ssim, ms_ssim  # noqa: E402
from sar_zero123.evaluation.paper_metrics import paper_kuan_ssim, paper_ms_ssim  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="MSTAR folder with index.csv")
    parser.add_argument("--num_pairs", type=int, default=100)
    parser.add_argument("--image_size", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args(argv)
    records = split_records(load_index(args.data), "extended")["test"]
    pairs = ViewPairDataset(records, size=args.image_size, seed=args.seed, num_pairs=args.num_pairs)
    x = torch.stack([pair["input"] for pair in pairs])
    y = torch.stack([pair["target"] for pair in pairs])
    scores = {
        "ms_ssim paper (256 px, 8-bit, torchmetrics 9x9)": paper_ms_ssim(x, y),
        f"ms_ssim paper at {args.image_size} px (no resize)": paper_ms_ssim(x, y, scoring_size=None),
        "ms_ssim corrected (7x7 Gaussian, generated size)": ms_ssim(x, y),
        "kuan_ssim paper (256 px, 8-bit, findpeaks + skimage)": paper_kuan_ssim(x, y),
        f"kuan_ssim paper at {args.image_size} px (no resize)": paper_kuan_ssim(x, y, scoring_size=None),
        "kuan_ssim corrected (centred 7x7 Kuan, Gaussian SSIM)": kuan_ssim(x, y),
    }
    names = list(scores)
    summary = {name: {"mean": float(v.mean()), "std": float(v.std())} for name, v in scores.items()}
    comparisons = {}
    for paper, corrected in ((names[0], names[2]), (names[3], names[5]), (names[0], names[1]),
                             (names[3], names[4])):
        difference = (scores[corrected] - scores[paper]).numpy()
        comparisons[f"{corrected} - {paper}"] = {
            "mean": float(difference.mean()),
            "mean_abs": float(np.abs(difference).mean()),
            "max_abs": float(np.abs(difference).max()),
            "correlation": float(np.corrcoef(scores[corrected].numpy(), scores[paper].numpy())[0, 1]),
        }
    result = {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": "python " + " ".join(sys.argv),
        "num_pairs": len(pairs),
        "image_size": args.image_size,
        "scores": summary,
        "differences": comparisons,
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return result


if __name__ == "__main__":
    main()
