"""The learned shortlist of the proxy fit: a network that ranks a proxy bank's vehicles for a chip.

    python train/train_proxy_retrieval.py --output_dir runs/proxy_retrieval

The flags are the fields of `sar_zero123.stages.proxy_retrieval.ProxyRetrievalConfig`; the stage is
`sar_zero123.stages.proxy_retrieval.run_proxy_retrieval` (simulator chips only, cached in `data.npz`; the
network in `retrieval/`, its held-out recall in `metrics.json`). The bundled `sar-zero123/proxy-retrieval`
is this command's output with its defaults (model card: `sar_zero123/pretrained/proxy_retrieval.md`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sar_zero123 import cli
from sar_zero123.stages.proxy_retrieval import ProxyRetrievalConfig

__all__ = ["ProxyRetrievalConfig", "main"]


def main(argv: Sequence[str] | None = None) -> Path:
    """Trains the network; returns its folder."""
    return cli.proxy_retrieval(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.proxy_retrieval())
