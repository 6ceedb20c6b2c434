"""Train an ``AutoencoderKL`` sized for SAR chips, for users without a pretrained VAE.

    accelerate launch train/train_vae.py [--data /path/to/mstar --protocol extended] [--flag value ...]

The flags are the fields of :class:`sar_zero123.stages.TrainVAEConfig`; the stage is
:func:`sar_zero123.stages.run_vae`. The model lands in ``output_dir/vae``
(``train/finetune_pfm.py --vae output_dir/vae``). A folder that already holds a run is continued only with
``--resume_from_checkpoint latest`` and started over only with ``--restart``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sar_zero123 import cli
from sar_zero123.stages.vae import TrainVAEConfig, VAEObjective, build_vae, reconstruct

__all__ = ["TrainVAEConfig", "VAEObjective", "build_vae", "main", "reconstruct"]


def main(argv: Sequence[str] | None = None) -> Path:
    """Train the VAE; returns the run folder (the model is in ``output_dir/vae``)."""
    return cli.vae(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.vae())
