"""Reading chip files as magnitude images, and bringing them to a common size.

``load_magnitude`` returns float32 magnitude for every file kind the project meets:

==========================  ======================================================
file                        magnitude
==========================  ======================================================
8-bit JPEG/PNG              pixel / 255 (the shared MSTAR JPEGs, SAMPLE PNGs)
16-bit PNG                  pixel / 65535
``.npy``                    the stored float array (the simulator writes [0, 1])
``.mat`` (SAMPLE)           ``abs(complex_img)``
original MSTAR (Phoenix)    the stored float magnitude (calibrated, not in [0, 1])
==========================  ======================================================
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image
from skimage.transform import resize

from sar_zero123.domain import center_crop

from .mstar_raw import is_mstar_raw, read_mstar_raw

__all__ = ["IMAGE_SUFFIXES", "MAX_CHIP_PIXELS", "MIN_CHIP_SIZE", "center_crop_resize", "load_magnitude"]

IMAGE_SUFFIXES = (".jpeg", ".jpg", ".png", ".tif", ".tiff", ".bmp")
#: Smallest side (pixels) of an image taken as a chip: upsampling a smaller one would invent the chip.
MIN_CHIP_SIZE = 16
#: Most pixels a chip file may declare, checked from its header so a huge claim allocates nothing.
MAX_CHIP_PIXELS = 4096 * 4096
# Keys of the complex image in SAMPLE .mat files, in order of preference.
_MAT_IMAGE_KEYS = ("complex_img", "complex_img_unshifted")


def _check_declared_size(path: Path, shape: tuple[int, ...]) -> None:
    """Refuse a file whose header declares more than :data:`MAX_CHIP_PIXELS` pixels, before decoding."""
    pixels = int(np.prod([int(n) for n in shape], dtype=object)) if shape else 1
    if pixels > MAX_CHIP_PIXELS:
        raise ValueError(
            f"{path}: the file declares a {' x '.join(str(int(n)) for n in shape)} image ({pixels:,} "
            f"values); a chip has at most {MAX_CHIP_PIXELS:,} (4096 x 4096): crop the target first"
        )


def _load_npy(path: Path) -> np.ndarray:
    """An ``.npy`` chip, its header checked (shape, type, and the bytes it needs) before the array is read."""
    try:
        with path.open("rb") as handle:
            version = np.lib.format.read_magic(handle)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(handle)
            else:  # 2.0, and 3.0 (the same layout with a UTF-8 header)
                shape, _, dtype = np.lib.format.read_array_header_2_0(handle)
            offset = handle.tell()
    except (OSError, ValueError, EOFError) as error:
        message = f"{path}: cannot read the .npy header ({error}); the file is truncated or corrupt"
        raise ValueError(message) from None
    if not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)):
        raise ValueError(f"{path}: .npy chip must hold real numbers, got dtype {dtype}")
    _check_declared_size(path, shape)
    needed = offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if path.stat().st_size < needed:
        raise ValueError(
            f"{path}: the .npy header declares {shape} {dtype} ({needed:,} bytes with the header) but the "
            f"file has {path.stat().st_size:,}; it is truncated"
        )
    try:
        return np.load(path, allow_pickle=False).astype(np.float32)
    except (OSError, ValueError, EOFError) as error:
        message = f"{path}: cannot read the .npy array ({error}); the file is truncated or corrupt"
        raise ValueError(message) from None


def _load_image_file(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as image:
            _check_declared_size(path, (image.height, image.width))  # from the header: nothing decoded yet
            if image.mode in ("RGB", "RGBA", "P", "LA"):
                # Grayscale stored as colour: the channels are equal for SAR chips; take luminance.
                image = image.convert("L")
            pixels = np.asarray(image)
    except Image.DecompressionBombError as error:  # PIL's own bound, checked as it opens the header
        raise ValueError(
            f"{path}: the file declares an image of more than {MAX_CHIP_PIXELS:,} pixels ({error}); a chip "
            "has at most 4096 x 4096: crop the target first"
        ) from None
    except (OSError, SyntaxError, ValueError) as error:
        if str(error).startswith(f"{path}: the file declares"):
            raise
        raise ValueError(
            f"{path}: cannot read the {path.suffix} image ({error}); the file is truncated, corrupt or not "
            "an image"
        ) from None
    if pixels.dtype == np.uint8:
        return pixels.astype(np.float32) / 255.0
    if pixels.dtype in (np.uint16, np.int32) and image.mode.startswith("I"):
        # PIL opens 16-bit PNGs as mode "I" / "I;16" (int32 or uint16 values up to 65535).
        return pixels.astype(np.float32) / 65535.0
    if pixels.dtype == np.bool_:
        return pixels.astype(np.float32)
    if np.issubdtype(pixels.dtype, np.floating):
        return pixels.astype(np.float32)
    raise ValueError(f"{path}: unsupported image pixel type {pixels.dtype} (mode {image.mode})")


def _load_mat(path: Path) -> np.ndarray:
    """A SAMPLE ``.mat`` chip: its variables listed first (nothing decoded), the image variable checked for
    its size and for holding numbers, then only that variable read."""
    from scipy.io import loadmat, whosmat
    from scipy.io.matlab import MatReadError

    try:
        listed = {name: (tuple(shape), kind) for name, shape, kind in whosmat(path)}
        key = next((k for k in _MAT_IMAGE_KEYS if k in listed), None)
        if key is None:
            raise ValueError(
                f"{path}: .mat file has none of the keys {list(_MAT_IMAGE_KEYS)}; it has {sorted(listed)}"
            )
        shape, kind = listed[key]
        if kind not in ("double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
                        "uint64"):  # fmt: skip
            raise ValueError(f"{path}: .mat variable {key!r} must hold numbers, got MATLAB class {kind!r}")
        _check_declared_size(path, shape)
        contents = loadmat(path, variable_names=[key])
    except ValueError as error:
        if str(error).startswith(str(path)):
            raise
        message = f"{path}: cannot read the .mat file ({error}); the file is truncated or corrupt"
        raise ValueError(message) from None
    except (MatReadError, OSError, TypeError) as error:
        message = f"{path}: cannot read the .mat file ({error}); the file is truncated or corrupt"
        raise ValueError(message) from None
    return np.abs(np.asarray(contents[key])).astype(np.float32)


def load_magnitude(path: str | Path) -> np.ndarray:
    """Reads a chip file as float32 magnitude (H, W), by the module table's convention for its kind.

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        ValueError: If the file cannot be read (naming it), declares more than :data:`MAX_CHIP_PIXELS` pixels
            (refused from its header), is not a single-channel 2-D image, or holds negative or non-finite
            magnitudes.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"chip file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        magnitude = _load_npy(path)
    elif suffix == ".mat":
        magnitude = _load_mat(path)
    elif suffix in IMAGE_SUFFIXES:
        magnitude = _load_image_file(path)
    elif is_mstar_raw(path):
        magnitude = read_mstar_raw(path).magnitude
    else:
        raise ValueError(
            f"{path}: unknown chip file kind; expected one of {list(IMAGE_SUFFIXES)}, .npy, .mat or an "
            "original MSTAR file"
        )
    if magnitude.ndim == 3 and magnitude.shape[0] == 1:
        magnitude = magnitude[0]
    if magnitude.ndim != 2:
        raise ValueError(f"{path}: expected a single-channel (H, W) image, got shape {magnitude.shape}")
    if not np.isfinite(magnitude).all():
        raise ValueError(f"{path}: magnitude contains non-finite values (NaN or inf); expected finite values")
    if (magnitude < 0).any():
        raise ValueError(f"{path}: magnitude contains negative values; expected magnitudes >= 0")
    return magnitude


def center_crop_resize(
    image: np.ndarray, size: int = 128, crop_size: int | None = None, name: str = "image"
) -> np.ndarray:
    """Centre-crops a chip (H, W) to a square and resizes it to float32 ``(size, size)``.

    With ``crop_size=None`` the crop keeps the pixel spacing whenever possible: a chip at least ``size``
    pixels on each side is cropped to ``size`` with no resampling; a smaller chip is cropped to its shorter
    side and upsampled. An explicit ``crop_size`` crops that square and resizes it (bilinear, anti-aliased
    when shrinking). An image with a side below :data:`MIN_CHIP_SIZE` (or ``size``, if smaller) is refused.

    Raises:
        ValueError: If ``image`` is not 2-D or too small to be a chip, ``size`` < 1, or ``crop_size``
            exceeds the image; ``name`` is the image in the message.
    """
    if image.ndim != 2:
        raise ValueError(f"{name} must have shape (H, W), got {image.shape}")
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    smallest = min(size, MIN_CHIP_SIZE)
    if min(image.shape) < smallest:
        raise ValueError(
            f"{name}: a {image.shape[0]}x{image.shape[1]} image is too small to be a chip; expected at least "
            f"{smallest}x{smallest} pixels (MIN_CHIP_SIZE = {MIN_CHIP_SIZE})"
        )
    if crop_size is None:
        crop_size = min(size, *image.shape)
    crop = center_crop(image, crop_size)
    if crop_size == size:
        return np.ascontiguousarray(crop, dtype=np.float32)
    resized = resize(crop, (size, size), order=1, mode="reflect", anti_aliasing=crop_size > size)
    return resized.astype(np.float32)
