"""The SAR encoder f: a ResNet-18 on normalised-dB chips, its SimCLR projection head and NT-Xent.

Pretrained with SimCLR on co-domain augmented views (Table I), then frozen: its 512-d pooled feature
h = f(x) is the feature space of PFM (Eq. 20) and the backbone of the evaluation models. The body is
transformers' ``ResNetModel``; the reference setting swaps its ImageNet stem (4x downsampling) for a
CIFAR-style 3x3 stride-1 stem without pooling, which keeps a small target's scattering centres resolved.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from torch import nn
from transformers import ResNetConfig, ResNetModel
from transformers.models.resnet.modeling_resnet import ResNetConvLayer

from sar_zero123.config.json_io import read_json
from sar_zero123.domain import unit_to_signed
from sar_zero123.model.loading import load_weights_file

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"


@dataclass
class SAREncoderConfig:
    """Architecture of the SAR encoder (``forward`` rejects chips of another ``image_size``).

    With ``in_channels=3`` (mirroring RGB backbones) 1-channel input is replicated to 3; the last of
    ``hidden_sizes`` is the feature dimension.
    """

    image_size: int = 128  # side of the square input chip in pixels
    in_channels: int = 1  # 1 for SAR magnitude, 3 to mirror RGB backbones
    cifar_stem: bool = True  # 3x3 stride-1 stem, no max-pool (reference setting for 128 px SAR)
    depths: tuple[int, ...] = (2, 2, 2, 2)  # ResNet-18
    hidden_sizes: tuple[int, ...] = (64, 128, 256, 512)  # stage widths; the last is the feature size
    embedding_size: int = 64  # stem width

    def __post_init__(self) -> None:
        self.depths = tuple(int(d) for d in self.depths)
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        if self.image_size < 8:
            raise ValueError(f"image_size must be >= 8, got {self.image_size}")
        if self.in_channels not in (1, 3):
            raise ValueError(f"in_channels must be 1 or 3, got {self.in_channels}")
        if len(self.depths) == 0 or len(self.depths) != len(self.hidden_sizes):
            raise ValueError(
                f"depths and hidden_sizes must be non-empty and of equal length, got {self.depths} "
                f"and {self.hidden_sizes}"
            )
        if min(self.depths) < 1:
            raise ValueError(f"depths must be >= 1, got {self.depths}")
        if min(self.hidden_sizes) < 1 or self.embedding_size < 1:
            raise ValueError(
                f"hidden_sizes and embedding_size must be positive, got {self.hidden_sizes}, "
                f"{self.embedding_size}"
            )

    def to_dict(self) -> dict:
        """The configuration as a JSON-serialisable dict."""
        out = dataclasses.asdict(self)
        out["depths"] = list(self.depths)
        out["hidden_sizes"] = list(self.hidden_sizes)
        return out

    @classmethod
    def from_dict(cls, values: dict) -> SAREncoderConfig:
        """A configuration from ``to_dict`` output, ignoring unknown keys (e.g. ``model_type``)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})


class SAREncoder(nn.Module):
    """ResNet-18 SAR encoder returning the pooled feature h = f(x).

    Example:
        >>> encoder = SAREncoder(SAREncoderConfig(image_size=64))
        >>> encoder(torch.rand(2, 1, 64, 64)).shape
        torch.Size([2, 512])
    """

    def __init__(self, config: SAREncoderConfig | None = None) -> None:
        super().__init__()
        self.config = config if config is not None else SAREncoderConfig()
        resnet_config = ResNetConfig(
            num_channels=self.config.in_channels,
            embedding_size=self.config.embedding_size,
            hidden_sizes=list(self.config.hidden_sizes),
            depths=list(self.config.depths),
            layer_type="basic",
            downsample_in_first_stage=False,
        )
        self.resnet = ResNetModel(resnet_config)
        if self.config.cifar_stem:
            # transformers has no option for the CIFAR stem: replace its convolution and pooling.
            stem = ResNetConvLayer(
                self.config.in_channels, self.config.embedding_size, kernel_size=3, stride=1
            )
            nn.init.kaiming_normal_(stem.convolution.weight, mode="fan_out", nonlinearity="relu")
            self.resnet.embedder.embedder = stem
            self.resnet.embedder.pooler = nn.Identity()

    @property
    def feature_dim(self) -> int:
        """Dimension of h = f(x) (512 for ResNet-18)."""
        return self.config.hidden_sizes[-1]

    @property
    def device(self) -> torch.device:
        """Device of the encoder's parameters."""
        return next(self.parameters()).device

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the encoder's parameters."""
        return next(self.parameters()).dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Encodes normalised-dB chips into pooled features h = f(x), differentiable in ``x``.

        Values are not range-checked, so decoded images slightly outside [0, 1] still pass.

        Shape:
            x: (B, C, image_size, image_size) with C == in_channels, or C == 1 when in_channels == 3.
            output: (B, feature_dim).

        Raises:
            ValueError: If ``x`` has the wrong rank, channel count or spatial size, or is not floating.
        """
        x = self._checked_input(x)
        # Zero-centre the [0, 1] normalised dB so the stem sees a symmetric input range.
        hidden = self.resnet(unit_to_signed(x), return_dict=True).pooler_output  # (B, D, 1, 1)
        return hidden.flatten(1)  # (B, D)

    def _checked_input(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` validated and expanded to ``in_channels`` (see :meth:`forward`)."""
        if x.ndim != 4:
            raise ValueError(f"x must have shape (B, C, H, W), got rank {x.ndim} shape {tuple(x.shape)}")
        if not torch.is_floating_point(x):
            raise ValueError(f"x must be a floating tensor, got dtype {x.dtype}")
        channels = x.shape[1]
        if channels != self.config.in_channels and not (channels == 1 and self.config.in_channels == 3):
            raise ValueError(f"x must have {self.config.in_channels} channels (in_channels), got {channels}")
        size = self.config.image_size
        if x.shape[-2:] != (size, size):
            raise ValueError(f"x must be {size}x{size} (image_size), got {tuple(x.shape[-2:])}")
        if channels != self.config.in_channels:
            x = x.expand(-1, self.config.in_channels, -1, -1)  # (B, 3, H, W)
        return x

    def save_pretrained(self, save_directory: str | Path) -> Path:
        """Writes ``config.json`` and ``model.safetensors`` into ``save_directory``; returns it.

        Hand-written instead of diffusers' ``ModelMixin`` so the folder holds exactly these two files and a
        missing folder never falls through to a Hub download.
        """
        directory = Path(save_directory)
        directory.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu().contiguous() for k, v in self.state_dict().items()}
        save_file(state, str(directory / WEIGHTS_NAME), metadata={"format": "pt"})
        payload = {"model_type": "sar_encoder", **self.config.to_dict()}
        (directory / CONFIG_NAME).write_text(json.dumps(payload, indent=2) + "\n")
        return directory

    @classmethod
    def from_pretrained(cls, pretrained_path: str | Path, device: str | torch.device = "cpu") -> SAREncoder:
        """Loads an encoder written by ``save_pretrained``, in eval mode.

        Raises:
            FileNotFoundError: If the folder or one of its two files is missing.
            ValueError: If ``config.json`` is not a valid config, or the weights are unreadable or do not fit
                it; the message names the file.
        """
        directory = Path(pretrained_path)
        for path in (directory / CONFIG_NAME, directory / WEIGHTS_NAME):
            if not path.is_file():
                raise FileNotFoundError(f"SAR encoder checkpoint not found: {path}")
        values = read_json(directory / CONFIG_NAME, what="a SAR encoder config (SAREncoderConfig.to_dict)")
        try:
            config = SAREncoderConfig.from_dict(values)
        except (AttributeError, TypeError, ValueError) as error:
            raise ValueError(f"{directory / CONFIG_NAME}: not a valid SAR encoder config ({error})") from None
        encoder = cls(config)
        load_weights_file(encoder, directory / WEIGHTS_NAME, f"the SAR encoder in {str(directory)!r}", device)
        return encoder.to(device).eval()


def resolve_encoder_dir(path: str | Path, field: str = "encoder") -> Path:
    """The folder holding a saved encoder: ``path`` itself or ``path/encoder`` (a SimCLR run folder).

    Raises:
        FileNotFoundError: If neither holds both files (naming ``field``).
    """
    path = Path(path)
    for candidate in (path, path / "encoder"):
        if (candidate / CONFIG_NAME).is_file() and (candidate / WEIGHTS_NAME).is_file():
            return candidate
    raise FileNotFoundError(
        f"{field}: no SAR encoder ({CONFIG_NAME} + {WEIGHTS_NAME}) in {path} or {path / 'encoder'}"
    )


class ProjectionHead(nn.Module):
    """SimCLR projection head g: Linear - ReLU - Linear (512-512-128 in the reference setting)."""

    def __init__(self, in_dim: int = 512, hidden_dim: int = 512, out_dim: int = 128) -> None:
        super().__init__()
        for name, value in (("in_dim", in_dim), ("hidden_dim", hidden_dim), ("out_dim", out_dim)):
            if value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        self.net = nn.Sequential(
            nn.Linear(in_dim, hidden_dim), nn.ReLU(inplace=True), nn.Linear(hidden_dim, out_dim)
        )

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """Projects features: (B, in_dim) -> (B, out_dim)."""
        return self.net(h)


class _GatherRows(torch.autograd.Function):
    """Differentiable all-gather of equal-sized (N, D) blocks into (W * N, D), rank order.

    torch's public differentiable gather is deprecated. The backward sums the gradient over the processes
    and keeps this process's rows (a reduce-scatter).
    """

    @staticmethod
    def forward(ctx, block: torch.Tensor) -> torch.Tensor:  # noqa: D102
        ctx.rows = block.shape[0]
        parts = [torch.empty_like(block) for _ in range(torch.distributed.get_world_size())]
        torch.distributed.all_gather(parts, block.contiguous())
        return torch.cat(parts)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # noqa: D102
        grad = grad.contiguous()
        torch.distributed.all_reduce(grad)
        start = torch.distributed.get_rank() * ctx.rows
        return grad[start : start + ctx.rows]


def nt_xent_loss(
    z1: torch.Tensor, z2: torch.Tensor, temperature: float = 0.5, *, gather_distributed: bool = False
) -> torch.Tensor:
    """Normalised temperature-scaled cross-entropy (SimCLR) for N positive pairs.

    With u = normalise(cat(z1, z2)) and s_ij = u_i . u_j / temperature, the anchor loss is
    l(i, j) = -log(exp(s_ij) / sum_{k != i} exp(s_ik)) where j is the other view of i. The loss of
    pair n is (l(n, n+N) + l(n+N, n)) / 2. Collapsed embeddings give log(2N - 1) for every pair.

    With ``gather_distributed`` in a process group of W processes, every local anchor is contrasted with the
    2NW projections of all processes (gathered with gradients), so the losses and averaged gradients equal
    those of one process holding the whole global batch.

    Returns:
        Per-pair loss of the local pairs, in float32 (also under autocast).

    Shape:
        z1, z2: (N, D) with N >= 1 and N x processes >= 2. output: (N,).

    Raises:
        ValueError: If shapes differ or are not (N, D), ``temperature`` is not positive, fewer than 2 pairs
            are contrasted, or (when gathering) the processes hold different numbers of pairs.
    """
    if z1.ndim != 2 or z1.shape != z2.shape:
        raise ValueError(f"z1 and z2 must both be (N, D), got {tuple(z1.shape)} and {tuple(z2.shape)}")
    if not (temperature > 0 and math.isfinite(temperature)):
        raise ValueError(f"temperature must be positive and finite, got {temperature}")
    n = z1.shape[0]
    u1, u2 = F.normalize(z1.float(), dim=1), F.normalize(z2.float(), dim=1)  # (N, D) each
    anchors = torch.cat([u1, u2])  # (2N, D)
    world, rank = 1, 0
    if gather_distributed and torch.distributed.is_available() and torch.distributed.is_initialized():
        world, rank = torch.distributed.get_world_size(), torch.distributed.get_rank()
    if world > 1:
        sizes = [torch.zeros(1, dtype=torch.long, device=u1.device) for _ in range(world)]
        torch.distributed.all_gather(sizes, torch.tensor([n], device=u1.device))
        if any(int(size) != n for size in sizes):
            counts = [int(size) for size in sizes]
            raise ValueError(f"gather_distributed needs equal pairs on every process, got {counts}")
        candidates = torch.cat([_GatherRows.apply(u1), _GatherRows.apply(u2)])  # (2NW, D): views 1, views 2
    else:
        candidates = anchors
    total = n * world
    if total < 2:  # a lone pair's only candidate is its positive: loss 0 and no gradient, silently
        raise ValueError(
            f"NT-Xent needs at least 2 pairs (the other pairs are the negatives), got {total}; use a larger "
            "batch (or gather negatives across processes)"
        )
    local = torch.arange(n, device=u1.device) + rank * n  # this process's rows among the first views
    self_index = torch.cat([local, local + total])  # (2N,) where each anchor sits among the candidates
    positives = torch.cat([local + total, local])  # (2N,) its other view
    logits = anchors @ candidates.T / temperature  # (2N, 2NW)
    is_self = torch.zeros_like(logits, dtype=torch.bool)
    is_self[torch.arange(2 * n, device=u1.device), self_index] = True
    per_anchor = F.cross_entropy(logits.masked_fill(is_self, float("-inf")), positives, reduction="none")
    return (per_anchor[:n] + per_anchor[n:]) / 2


__all__ = [
    "CONFIG_NAME",
    "WEIGHTS_NAME",
    "ProjectionHead",
    "SAREncoder",
    "SAREncoderConfig",
    "nt_xent_loss",
    "resolve_encoder_dir",
]
