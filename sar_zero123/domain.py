"""The SAR domain's shared conventions: decibels, the signed and unit ranges, the centre crop, index.csv,
and how a failed write is reported.

Imports nothing from the rest of the package and not torch (the simulator is numpy only).

Conventions::

    db = 20 * log10(m + 1e-3)      # to_decibels; zero magnitude is -60 dB
    x_signed = 2 * x_unit - 1      # unit_to_signed: normalised dB [0, 1] -> [-1, 1]
"""

from __future__ import annotations

import re
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch

__all__ = [
    "DB_EPS",
    "INDEX_COLUMNS",
    "INDEX_FILENAME",
    "MAX_IMAGE_SIZE",
    "Array",
    "center_crop",
    "from_decibels",
    "is_tensor",
    "naming_write_errors",
    "read_number",
    "signed_to_unit",
    "to_decibels",
    "unit_to_signed",
]

#: Added to magnitudes before the logarithm, so zero magnitude is -60 dB rather than -inf.
DB_EPS = 1e-3

#: The largest chip side in pixels any stage or command works at (4x the zero-1-to-3 resolution; the
#: allocations grow with its square): a bound on what ``image_size`` and the scoring sizes allocate,
#: checked by each config before any chip is read or simulated.
MAX_IMAGE_SIZE = 1024

#: The file that lists a chip folder's chips, one row per chip.
INDEX_FILENAME = "index.csv"
#: The columns of ``index.csv`` in the order every writer of the package writes them (the simulator, the
#: dataset augmentation, :func:`sar_zero123.data.write_index`, which may add ``mstar_source``).
INDEX_COLUMNS = (
    "path",
    "target_class",
    "target_type",
    "serial",
    "depression_deg",
    "azimuth_deg",
    "height",
    "width",
)

Array = TypeVar("Array", "np.ndarray", "torch.Tensor")


def is_tensor(value: Any) -> bool:
    """Whether ``value`` is a torch tensor, without importing torch (no tensor exists before it is)."""
    torch_module = sys.modules.get("torch")
    return torch_module is not None and isinstance(value, torch_module.Tensor)


def to_decibels(magnitude: Array) -> Array:
    """Magnitude to decibels, ``20 * log10(m + 1e-3)`` (zero magnitude maps to -60 dB); arrays or tensors,
    same type, shape and floating dtype."""
    if is_tensor(magnitude):
        return 20.0 * (magnitude + DB_EPS).log10()
    return (20.0 * np.log10(np.asarray(magnitude) + DB_EPS)).astype(np.result_type(magnitude, np.float32))


def from_decibels(decibels: Array) -> Array:
    """Inverse of :func:`to_decibels`: ``10 ** (db / 20) - 1e-3``; arrays or tensors."""
    if is_tensor(decibels):
        return 10.0 ** (decibels / 20.0) - DB_EPS
    return (np.power(10.0, np.asarray(decibels) / 20.0) - DB_EPS).astype(np.result_type(decibels, np.float32))


def unit_to_signed(x: Array) -> Array:
    """Normalised dB in [0, 1] -> [-1, 1], the input range of the VAE and of the SAR encoder's ResNet."""
    return x * 2.0 - 1.0


def signed_to_unit(x: Array) -> Array:
    """[-1, 1] (a VAE's decoded image) -> normalised dB in [0, 1]; no clipping."""
    return (x + 1.0) / 2.0


def center_crop(image: Array, crop_size: int) -> Array:
    """Cuts the central ``crop_size x crop_size`` square (the target sits at the chip centre); the package's
    one centre crop, for arrays and tensors.

    For an odd margin the extra row/column is dropped at the end.

    Shape:
        ``(..., H, W) -> (..., crop_size, crop_size)`` (a view).

    Raises:
        ValueError: If the image is smaller than ``crop_size`` or ``crop_size`` < 1.
    """
    height, width = image.shape[-2:]
    if crop_size < 1:
        raise ValueError(f"crop_size must be >= 1, got {crop_size}")
    if height < crop_size or width < crop_size:
        raise ValueError(f"image of size {height}x{width} is smaller than crop_size={crop_size}")
    top = (height - crop_size) // 2
    left = (width - crop_size) // 2
    return image[..., top : top + crop_size, left : left + crop_size]


#: A number as the package's text inputs write one (flags, ``--set``, ``index.csv``): ASCII digits, a sign, a
#: decimal point, an exponent, or a name of an infinity or NaN (refused as such by the reader).
_NUMBER_TEXT = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:e[+-]?\d+)?|[+-]?(?:inf|infinity|nan)", re.I | re.A)
_INTEGER_TEXT = re.compile(r"[+-]?\d+", re.A)


def read_number(text: str, integer: bool = False) -> float | int:
    """The number ``text`` writes, read strictly: Python also reads ``"3_0"`` and non-ASCII digits as 30,
    which no user means.

    Returns:
        The ``int`` (with ``integer``) or ``float``, possibly infinite or NaN for the caller to refuse.

    Raises:
        ValueError: For any other text.
    """
    stripped = text.strip()
    if not (_INTEGER_TEXT if integer else _NUMBER_TEXT).fullmatch(stripped):
        raise ValueError(f"not {'an integer' if integer else 'a number'}: {text!r}")
    return int(stripped) if integer else float(stripped)


#: How torch.save's writer reports a failed write (a full disk), as a RuntimeError rather than an OSError.
_TORCH_WRITER_FAILURE = re.compile(
    r"enforce fail at inline_container|PytorchStreamWriter failed", re.IGNORECASE
)


@contextmanager
def naming_write_errors(path: Any, kept: str) -> Iterator[None]:
    """Around a write: a failed write (disk full, a file-size limit, a read-only folder) is raised as an
    ``OSError`` naming ``path`` and what was ``kept``, instead of a bare ``[Errno 28]`` naming neither.
    Nested, the outermost names its ``path`` and the innermost file in brackets.

    Raises:
        OSError: With the original ``errno`` (``None`` for safetensors), the original error chained.
    """
    try:
        yield
    except Exception as error:
        inner = getattr(error, "_write_failure", None)  # (file, reason) of an inner naming_write_errors
        if inner is None and isinstance(error, OSError):
            inner = (getattr(error, "filename", None), error.strerror or str(error))
        elif inner is None and type(error).__name__ == "SafetensorError":  # not an OSError
            inner = (None, str(error))
        elif inner is None and isinstance(error, RuntimeError) and _TORCH_WRITER_FAILURE.search(str(error)):
            # torch.save's zip writer on a full disk: "[enforce fail at inline_container.cc] unexpected pos"
            inner = (None, f"PyTorch's file writer failed ({str(error).strip()[:120]}): is the disk full?")
        if inner is None:
            raise
        file, reason = inner
        where = f" ({file})" if file is not None and str(file) != str(path) else ""
        message = f"could not write {str(path)!r}{where}: {reason}; {kept}"
        errno = getattr(error, "errno", None)
        named = OSError(errno, message) if errno is not None else OSError(message)
        named._write_failure = (file if file is not None else str(path), reason)  # type: ignore[attr-defined]
        raise named from error
