"""Contact sheet: real MSTAR chips beside their simulator proxies (issue 61)

    python benchmarks/proxy_contact_sheet.py --mstar ../shared/data/mstar \
        --out docs/figures/proxy_contact_sheet.png

One 17 deg chip per MSTAR class (a 64 px centre crop at the native 0.2 m spacing, the first of its class in
index order), the bundled prior's proxy fitted to it at its header pose (the bank vehicle whose render
correlates best with it), and the same proxy turned by 90 deg: what the generator starts from when asked
for that turn. Prints each fit's correlation.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from _common import script_parser
from matplotlib.figure import Figure

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline, resolve_pretrained
from sar_zero123.data import SCALING_FILE, DecibelScaling, load_chip
from sar_zero123.model.proxy import draft_target_views
from sar_zero123.sim.proxy import blurred_correlation

DEPRESSION_DEG, SIZE, TURN_DEG = 17.0, 64, 90.0


def main(argv: Sequence[str] | None = None) -> Path:
    parser = script_parser(__doc__)
    parser.add_argument("--mstar", required=True, help="MSTAR folder with index.csv")
    parser.add_argument("--out", default="proxy_contact_sheet.png", help="output PNG")
    args = parser.parse_args(argv)
    index = Path(args.mstar) / "index.csv"
    if not index.is_file():
        raise FileNotFoundError(f"--mstar: no index.csv in {args.mstar!r}")
    with open(index, newline="") as handle:
        rows = [r for r in csv.DictReader(handle) if float(r["depression_deg"]) == DEPRESSION_DEG]
    first: dict[str, dict] = {}
    for row in rows:
        first.setdefault(row["target_class"], row)
    pipe = SARZero123Pipeline.from_pretrained(SIM_PRIOR_ROTATED)
    scaling = DecibelScaling.from_file(resolve_pretrained(SIM_PRIOR_ROTATED) / SCALING_FILE)
    names = sorted(first)
    figure = Figure(figsize=(1.6 * len(names), 5.2))
    axes = figure.subplots(3, len(names), squeeze=False)
    for column, name in enumerate(names):
        row = first[name]
        magnitude = load_chip(Path(args.mstar) / row["path"], SIZE, crop_size=SIZE)
        chip = scaling.normalize(magnitude).astype(np.float32)
        azimuth = float(row["azimuth_deg"])
        images = torch.from_numpy(chip)[None, None]
        pose = (torch.tensor([azimuth]), torch.tensor([DEPRESSION_DEG]))
        drafts = []
        for d_az in (0.0, TURN_DEG):
            request = (torch.tensor([d_az]), torch.zeros(1))
            draft, _ = draft_target_views(images, *pose, *request, pipe.config.proxy)
            drafts.append(draft[0, 0].numpy())
        score = float(blurred_correlation(chip, drafts[0][None], pipe.config.proxy["blur_sigma_px"])[0])
        print(f"{name}: azimuth {azimuth:.1f} deg, fit correlation {score:.3f}")
        titles = [f"{name}\naz {azimuth:.0f}", f"proxy (r {score:.2f})", f"proxy, +{TURN_DEG:g} deg"]
        for axis, image, title in zip(axes[:, column], [chip, *drafts], titles):
            axis.imshow(image, cmap="gray", vmin=0.0, vmax=1.0)
            axis.set_title(title, fontsize=7)
            axis.set_axis_off()
    figure.tight_layout()
    out = Path(args.out)
    figure.savefig(out, dpi=110)
    return out


if __name__ == "__main__":
    main()
