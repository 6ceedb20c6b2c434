"""Tests for the SAMPLE reader on a fabricated folder in the public release's layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.io import savemat

from sar_zero123.data import load_magnitude, load_sample, parse_sample_name

NAMES = [
    ("2s1", "elevDeg_015_azCenter_010_22_serial_b01"),
    ("2s1", "elevDeg_016_azCenter_011_22_serial_b01"),
    ("m1", "elevDeg_017_azCenter_079_18_serial_0ap00n"),
]


@pytest.fixture
def sample_root(tmp_path: Path) -> Path:
    for kind, value in (("real", 60), ("synth", 200)):
        for target, rest in NAMES:
            name = f"{target}_{kind}_A_{rest}"
            for variant in ("qpm", "decibel"):
                folder = tmp_path / "png_images" / variant / kind / target
                folder.mkdir(parents=True, exist_ok=True)
                Image.fromarray(np.full((4, 4), value, dtype=np.uint8)).save(folder / f"{name}.png")
            folder = tmp_path / "mat_files" / kind / target
            folder.mkdir(parents=True, exist_ok=True)
            savemat(folder / f"{name}.mat", {"complex_img": np.full((4, 4), value * 1j), "azimuth": 10.22})
    # a real chip without a synthetic twin is left out
    folder = tmp_path / "png_images" / "qpm" / "real" / "m1"
    Image.fromarray(np.zeros((4, 4), dtype=np.uint8)).save(
        folder / "m1_real_A_elevDeg_017_azCenter_080_18_serial_0ap00n.png"
    )
    return tmp_path


def test_parse_sample_name() -> None:
    kind, record = parse_sample_name("/x/2s1_real_A_elevDeg_015_azCenter_010_22_serial_b01.png")
    assert kind == "real"
    assert (record.target_class, record.target_type, record.serial) == ("2S1", "2s1", "b01")
    assert (record.depression_deg, record.azimuth_deg) == (15.0, 10.22)
    with pytest.raises(ValueError, match="not a SAMPLE file name"):
        parse_sample_name("/x/HB03787.002.jpeg")


@pytest.mark.parametrize("image_format", ["qpm", "decibel", "mat"])
def test_load_sample_pairs(sample_root: Path, image_format: str) -> None:
    pairs = load_sample(sample_root, image_format=image_format)
    assert [(p.real.target_class, p.real.depression_deg, p.real.azimuth_deg) for p in pairs] == [
        ("2S1", 15.0, 10.22),
        ("2S1", 16.0, 11.22),
        ("M1", 17.0, 79.18),
    ]
    for pair in pairs:
        assert "_real_" in pair.real.path.name and "_synth_" in pair.synth.path.name
        assert pair.real.path.name.replace("_real_", "_synth_") == pair.synth.path.name
    expected = (60.0, 200.0) if image_format == "mat" else (60 / 255, 200 / 255)
    np.testing.assert_allclose(load_magnitude(pairs[0].real.path), expected[0], rtol=1e-6)
    np.testing.assert_allclose(load_magnitude(pairs[0].synth.path), expected[1], rtol=1e-6)


def test_load_sample_errors(sample_root: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    with pytest.raises(ValueError, match="image_format must be one of"):
        load_sample(sample_root, image_format="jpeg")
    empty = tmp_path_factory.mktemp("empty")
    with pytest.raises(FileNotFoundError, match=r"png_images/qpm/real"):
        load_sample(empty)
    stray = "m1_real_A_elevDeg_017_azCenter_081_18_serial_0ap00n.png"
    Image.fromarray(np.zeros((4, 4), dtype=np.uint8)).save(sample_root / "png_images/qpm/synth/m1" / stray)
    with pytest.raises(ValueError, match="a 'real' chip inside the 'synth' folder"):
        load_sample(sample_root)
