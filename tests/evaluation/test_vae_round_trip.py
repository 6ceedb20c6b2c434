"""A VAE round trip in chunks equals one call, and the round-trip table reads its rows."""

from __future__ import annotations

import torch
from diffusers import AutoencoderKL

from sar_zero123.evaluation.tables import vae_round_trip_markdown
from sar_zero123.model.vae import reconstruct, reconstruct_in_batches


def test_round_trip_in_chunks_equals_one_reconstruction() -> None:
    torch.manual_seed(0)
    vae = AutoencoderKL(in_channels=1, out_channels=1, down_block_types=("DownEncoderBlock2D",) * 2,
                        up_block_types=("UpDecoderBlock2D",) * 2, block_out_channels=(8, 8),
                        layers_per_block=1, latent_channels=4, norm_num_groups=4).eval()  # fmt: skip
    images = torch.rand(5, 1, 16, 16)
    chunked = reconstruct_in_batches(vae, images, batch_size=2)
    assert chunked.shape == images.shape
    torch.testing.assert_close(chunked, reconstruct(vae, images), rtol=1e-5, atol=1e-6)
    assert float(chunked.min()) >= 0.0 and float(chunked.max()) <= 1.0


def test_markdown_has_one_line_per_row_and_group_with_standard_errors() -> None:
    values = {"accuracy": 94.5, "accuracy_se": 1.1413, "azimuth_error_deg": 18.72,
              "azimuth_error_deg_se": 1.87, "sfd": 0.19, "ms_ssim": 0.8317, "ms_ssim_se": 0.0015,
              "kuan_ssim": 0.7338, "n": 400.0}  # fmt: skip
    text = vae_round_trip_markdown({"prior VAE": {"seen": values, "unseen": {**values, "accuracy_se": 0.0}}})
    lines = text.strip().splitlines()
    assert len(lines) == 4
    expected = "| prior VAE | seen | 94.5 ± 1.1 | 18.7 ± 1.9 | 0.19 | 0.8317 ± 0.0015 | 0.7338 | 400 |"
    assert lines[2] == expected
    assert lines[3].startswith("| prior VAE | unseen | 94.5 | 18.7 ± 1.9 |")
