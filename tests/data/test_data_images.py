"""Tests for reading chip files as magnitude and for centre crop + resize."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.io import savemat

from sar_zero123.data import center_crop, center_crop_resize, load_magnitude


def test_8bit_png_is_pixel_over_255(tmp_path: Path) -> None:
    pixels = np.array([[0, 51], [255, 128]], dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "c.png")
    magnitude = load_magnitude(tmp_path / "c.png")
    assert magnitude.dtype == np.float32
    np.testing.assert_allclose(magnitude, [[0.0, 0.2], [1.0, 128 / 255]], rtol=1e-6)


def test_16bit_png_is_pixel_over_65535(tmp_path: Path) -> None:
    pixels = np.array([[0, 65535], [13107, 300]], dtype=np.uint16)
    Image.fromarray(pixels).save(tmp_path / "c16.png")
    np.testing.assert_allclose(load_magnitude(tmp_path / "c16.png"), [[0, 1], [0.2, 300 / 65535]], rtol=1e-6)


def test_jpeg_and_npy_and_mat(tmp_path: Path) -> None:
    Image.fromarray(np.full((8, 8), 200, dtype=np.uint8)).save(tmp_path / "c.jpeg", quality=95)
    np.testing.assert_allclose(load_magnitude(tmp_path / "c.jpeg"), 200 / 255, atol=2 / 255)
    chip = np.random.default_rng(0).uniform(size=(3, 4)).astype(np.float32)
    np.save(tmp_path / "c.npy", chip)
    np.testing.assert_array_equal(load_magnitude(tmp_path / "c.npy"), chip)
    savemat(tmp_path / "c.mat", {"complex_img": np.array([[3 + 4j, -1j]]), "azimuth": 10.2})
    np.testing.assert_allclose(load_magnitude(tmp_path / "c.mat"), [[5.0, 1.0]])


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.array([[0.1, np.inf]], dtype=np.float32), "non-finite"),
        (np.array([[0.1, -0.2]], dtype=np.float32), "negative values"),
        (np.zeros((2, 3, 3), dtype=np.float32), r"single-channel \(H, W\) image, got shape \(2, 3, 3\)"),
    ],
)
def test_bad_magnitudes(tmp_path: Path, array: np.ndarray, message: str) -> None:
    np.save(tmp_path / "bad.npy", array)
    with pytest.raises(ValueError, match=f"bad.npy: .*{message}"):
        load_magnitude(tmp_path / "bad.npy")


def test_missing_and_unknown_files(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="gone.png"):
        load_magnitude(tmp_path / "gone.png")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(ValueError, match="unknown chip file kind"):
        load_magnitude(tmp_path / "x.txt")
    savemat(tmp_path / "m.mat", {"other": np.ones(2)})
    with pytest.raises(ValueError, match=r"none of the keys \['complex_img'"):
        load_magnitude(tmp_path / "m.mat")


def test_a_file_declaring_a_huge_image_is_refused_from_its_header(tmp_path: Path) -> None:
    """A 5,000 and a 20,000 px PNG, an .npy header of 100,000 x 100,000 (37 GiB) and a .mat variable of
    5,000 x 5,000 are refused naming the declared size, before any pixel is decoded; a truncated .npy and a
    .mat image that holds text are refused by name too; the bound itself still loads."""
    import struct
    import tracemalloc
    import zlib

    from scipy.io import savemat

    from sar_zero123.data.images import MAX_CHIP_PIXELS

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    # a 20,000 x 20,000 PNG header with an empty image stream: a few dozen bytes claiming 400 M pixels
    header = chunk(b"IHDR", struct.pack(">IIBBBBB", 20_000, 20_000, 8, 0, 0, 0, 0))
    stream = chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")
    (tmp_path / "bomb.png").write_bytes(b"\x89PNG\r\n\x1a\n" + header + stream)
    Image.new("L", (5000, 5000)).save(tmp_path / "big.png")
    header = tmp_path / "header.npy"
    with header.open("wb") as handle:  # a valid header claiming 100,000 x 100,000 float32, and no data
        np.lib.format.write_array_header_1_0(handle, {"descr": "<f4", "fortran_order": False,
                                                      "shape": (100_000, 100_000)})  # fmt: skip
    savemat(tmp_path / "wide.mat", {"complex_img": np.zeros((5000, 5000), np.complex64)})
    tracemalloc.start()
    for name, size in (("big.png", "5000 x 5000"), ("header.npy", "100000 x 100000"),
                       ("wide.mat", "5000 x 5000")):  # fmt: skip
        words = rf"{name}: the file declares a {size} image \(.* values\); a chip"
        with pytest.raises(ValueError, match=words):
            load_magnitude(tmp_path / name)
    words = r"bomb.png: the file declares an image of more than 16,777,216 pixels"
    with pytest.raises(ValueError, match=words):  # above PIL's own bound, which refuses it as it opens
        load_magnitude(tmp_path / "bomb.png")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 64 * 2**20  # nothing near the declared sizes was allocated
    short = tmp_path / "short.npy"
    np.save(short, np.ones((32, 32), np.float32))
    short.write_bytes(short.read_bytes()[:-100])
    words = r"short.npy: the .npy header declares \(32, 32\) float32 .* truncated"
    with pytest.raises(ValueError, match=words):
        load_magnitude(short)
    savemat(tmp_path / "text.mat", {"complex_img": "not an image"})
    words = r"text.mat: .mat variable 'complex_img' must hold numbers, got .*'char'"
    with pytest.raises(ValueError, match=words):
        load_magnitude(tmp_path / "text.mat")
    side = int(MAX_CHIP_PIXELS**0.5)
    np.save(tmp_path / "edge.npy", np.zeros((side, side), np.float32))
    assert load_magnitude(tmp_path / "edge.npy").shape == (side, side)


def test_center_crop_keeps_pixels_of_large_chips() -> None:
    image = np.arange(193 * 192, dtype=np.float32).reshape(193, 192)
    out = center_crop_resize(image, size=128)
    # margins 65 rows (32 top, 33 bottom) and 64 columns (32 each side): a pure slice, no resampling
    np.testing.assert_array_equal(out, image[32:160, 32:160])
    assert out.flags["C_CONTIGUOUS"] and out.dtype == np.float32


def test_center_crop_resize_small_and_explicit_crop() -> None:
    image = np.ones((60, 64), dtype=np.float32)
    image[:, 32:] = 3.0
    up = center_crop_resize(image, size=120)  # crop 60x60 (columns 2..61), upsample x2
    assert up.shape == (120, 120)
    assert up[:, :55].max() == pytest.approx(1.0) and up[:, 65:].min() == pytest.approx(3.0)
    down = center_crop_resize(np.ones((10, 10), dtype=np.float32), size=4, crop_size=8)
    np.testing.assert_allclose(down, 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="smaller than crop_size=12"):
        center_crop(np.ones((10, 10)), 12)
    with pytest.raises(ValueError, match=r"image must have shape \(H, W\)"):
        center_crop_resize(np.ones((1, 10, 10)), 4)
