"""Tests for the original MSTAR reader and the raw-folder index (fabricated files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mstar_files import write_mstar

from sar_zero123.data import load_index, load_magnitude, read_mstar_raw, target_class_from_type

SHARED_MSTAR = Path(__file__).resolve().parents[3] / "shared" / "data" / "mstar"


@pytest.fixture
def chip_arrays() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return rng.rayleigh(0.1, size=(6, 5)).astype(np.float32), rng.uniform(0, 6.28, (6, 5)).astype(np.float32)


def test_read_round_trip(tmp_path: Path, chip_arrays: tuple[np.ndarray, np.ndarray]) -> None:
    magnitude, phase = chip_arrays
    chip = read_mstar_raw(write_mstar(tmp_path / "HB00001.000", magnitude, phase))
    np.testing.assert_array_equal(chip.magnitude, magnitude)
    np.testing.assert_array_equal(chip.phase, phase)
    assert chip.magnitude.dtype == np.float32 and chip.magnitude.shape == (6, 5)
    assert (chip.target_type, chip.serial, chip.target_class) == ("t72_tank", "132", "T72")
    assert chip.azimuth_deg == 271.5  # neither folded to -88.5 nor truncated
    assert chip.depression_deg == 17.0
    assert chip.header["MeasuredDepression"] == "17.093750"
    np.testing.assert_array_equal(load_magnitude(tmp_path / "HB00001.000"), magnitude)


def test_magnitude_only_file_has_no_phase(tmp_path: Path, chip_arrays: tuple[np.ndarray, np.ndarray]) -> None:
    chip = read_mstar_raw(write_mstar(tmp_path / "c", chip_arrays[0]))
    assert chip.phase is None
    np.testing.assert_array_equal(chip.magnitude, chip_arrays[0])


@pytest.mark.parametrize(
    ("target_type", "expected"),
    [("bmp2_tank", "BMP2"), ("zsu23-4_gun", "ZSU234"), ("2s1_gun", "2S1"), ("slicey", "SLICEY")],
)
def test_target_class_from_type(target_type: str, expected: str) -> None:
    assert target_class_from_type(target_type) == expected


def test_truncated_file(tmp_path: Path, chip_arrays: tuple[np.ndarray, np.ndarray]) -> None:
    path = write_mstar(tmp_path / "short", chip_arrays[0], declared_shape=(7, 5))
    with pytest.raises(ValueError, match=r"short: truncated MSTAR file: header declares 7 x 5"):
        read_mstar_raw(path)


@pytest.mark.parametrize("field", ["NumberOfRows", "TargetAz", "TargetSerNum", "DesiredDepression"])
def test_missing_header_field(tmp_path: Path, chip_arrays: tuple[np.ndarray, np.ndarray], field: str) -> None:
    path = write_mstar(tmp_path / "c", chip_arrays[0], drop=(field,))
    with pytest.raises(ValueError, match=f"no required field '{field}'"):
        read_mstar_raw(path)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"TargetAz": "360.0"}, r"'TargetAz' must lie in \[0, 360\)"),
        ({"TargetAz": "-1"}, r"'TargetAz' must lie in \[0, 360\)"),
        ({"TargetAz": "north"}, "'TargetAz' must be float"),
        ({"NumberOfRows": "six"}, "'NumberOfRows' must be int"),
    ],
)
def test_bad_header_values(
    tmp_path: Path, chip_arrays: tuple[np.ndarray, np.ndarray], fields, message
) -> None:
    with pytest.raises(ValueError, match=message):
        read_mstar_raw(write_mstar(tmp_path / "c", chip_arrays[0], fields=fields))


def test_non_finite_magnitude(tmp_path: Path, chip_arrays: tuple[np.ndarray, np.ndarray]) -> None:
    magnitude = chip_arrays[0].copy()
    magnitude[2, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        read_mstar_raw(write_mstar(tmp_path / "c", magnitude))


def test_not_an_mstar_file(tmp_path: Path) -> None:
    (tmp_path / "x.bin").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="starting with '\\[PhoenixHeader'"):
        read_mstar_raw(tmp_path / "x.bin")
    with pytest.raises(FileNotFoundError, match="missing"):
        read_mstar_raw(tmp_path / "missing")


def test_raw_folder_index_is_cached(tmp_path: Path, chip_arrays, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "a" / "b").mkdir(parents=True)
    write_mstar(tmp_path / "a" / "HB1.000", chip_arrays[0], fields={"TargetAz": "10.25"})
    bmp2 = {"TargetType": "bmp2_tank", "TargetSerNum": "c21"}
    write_mstar(tmp_path / "a" / "b" / "HB2.000", chip_arrays[0], fields=bmp2)
    (tmp_path / "notes.txt").write_text("not a chip")
    records = load_index(tmp_path)
    assert [(r.path.name, r.target_class, r.serial, r.azimuth_deg) for r in records] == [
        ("HB1.000", "T72", "132", 10.25),
        ("HB2.000", "BMP2", "c21", 271.5),
    ]
    assert (tmp_path / "index.csv").is_file()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp file left

    # 2nd call reads the cached index instead of the headers
    import sar_zero123.data.index as index_module

    monkeypatch.setattr(index_module, "read_mstar_raw", lambda path: pytest.fail(f"rescanned {path}"))
    assert load_index(tmp_path) == records


def test_raw_folder_with_bad_file_writes_no_index(tmp_path: Path, chip_arrays) -> None:
    write_mstar(tmp_path / "good", chip_arrays[0])
    write_mstar(tmp_path / "bad", chip_arrays[0], declared_shape=(9, 9))
    with pytest.raises(ValueError, match="bad: truncated"):
        load_index(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad", "good"]


@pytest.mark.shared_data
@pytest.mark.skipif(not (SHARED_MSTAR / "raw" / "HB03787.002").is_file(), reason="shared MSTAR data absent")
def test_shared_raw_chip_matches_jpeg() -> None:
    chip = read_mstar_raw(SHARED_MSTAR / "raw" / "HB03787.002")
    assert chip.magnitude.shape == (128, 128) and chip.phase is not None
    assert (chip.target_class, chip.serial, chip.depression_deg) == ("BMP2", "c21", 17.0)
    assert chip.azimuth_deg == pytest.approx(13.191422)
    jpeg = load_magnitude(SHARED_MSTAR / "chips" / "17deg" / "BMP2" / "HB03787.002.jpeg")
    correlation = np.corrcoef(chip.magnitude.ravel() / chip.magnitude.max(), jpeg.ravel())[0, 1]
    assert correlation > 0.9


def test_header_length_shorter_than_header(tmp_path: Path, chip_arrays) -> None:
    path = write_mstar(tmp_path / "c", chip_arrays[0])
    text = path.read_bytes()
    start = text.index(b"PhoenixHeaderLength= ") + len(b"PhoenixHeaderLength= ")
    path.write_bytes(text[:start] + b"00100" + text[start + 5 :])
    with pytest.raises(ValueError, match=r"'PhoenixHeaderLength' \(100\) must cover the ASCII header"):
        read_mstar_raw(path)


def test_read_only_raw_folder_is_not_cached(tmp_path: Path, chip_arrays) -> None:
    folder = tmp_path / "ro"
    folder.mkdir()
    write_mstar(folder / "HB1.000", chip_arrays[0])
    folder.chmod(0o555)
    try:
        with pytest.warns(UserWarning, match="read-only folder, index not cached"):
            records = load_index(folder)
    finally:
        folder.chmod(0o755)
    assert len(records) == 1 and sorted(p.name for p in folder.iterdir()) == ["HB1.000"]


def _edit_field(path: Path, field: str, value: str) -> Path:
    """Rewrites one header value in place (same width, so the header length stays right)."""
    text = path.read_bytes()
    start = text.index(f"{field}= ".encode()) + len(field) + 2
    end = text.index(b"\n", start)
    path.write_bytes(text[:start] + value.encode().ljust(end - start) + text[end:])
    return path


def _cut(count: int):
    return lambda path: path.write_bytes(path.read_bytes()[:-count])


def _append(count: int):
    return lambda path: path.write_bytes(path.read_bytes() + b"\0" * count)


def _edit(field: str, value: str):
    return lambda path: _edit_field(path, field, value)


# a 6 x 5 float32 chip: 120 bytes per plane after a 239-byte header, 479 bytes in all
@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (_cut(1), r"truncated MSTAR file: .*should have 359 or 479 bytes, but it has 478 \(the phase"),
        (_cut(121), r"truncated MSTAR file: .*but it has 358 \(the magnitude plane is incomplete\)"),
        (_append(8), r"MSTAR file longer than its header declares: .*\(8 bytes after the phase plane\)"),
        (_edit("NumberOfRows", "3"), r"MSTAR file longer .*declares 3 x 5 float32 .*\(120 bytes after"),
        (_edit("NumberOfRows", "7"), r"truncated MSTAR file: header declares 7 x 5 .*phase plane is"),
        (_edit("native_header_length", "4"), r"truncated .*native_header_length=4 bytes, .*phase plane is"),
    ],
    ids=["cut-by-1-byte", "magnitude-cut", "trailing-bytes", "rows-edited-down", "rows-edited-up",
         "native-header-length-edited"],
)  # fmt: skip
def test_file_length_must_match_the_header(tmp_path: Path, chip_arrays, damage, message) -> None:
    path = write_mstar(tmp_path / "HB9.000", *chip_arrays)
    assert path.stat().st_size == 479
    damage(path)
    with pytest.raises(ValueError, match=rf"HB9.000: {message}"):
        read_mstar_raw(path)


def test_cached_raw_folder_index_is_rescanned_when_a_file_is_added(tmp_path: Path, chip_arrays) -> None:
    write_mstar(tmp_path / "HB1.000", chip_arrays[0])
    assert len(load_index(tmp_path)) == 1
    write_mstar(tmp_path / "HB2.000", chip_arrays[0], fields={"TargetAz": "20.5"})
    stale = r"index.csv: cached index of a raw MSTAR folder is stale \(.*HB2.000 is not in the index\)"
    with pytest.warns(UserWarning, match=stale):
        records = load_index(tmp_path)
    assert [r.path.name for r in records] == ["HB1.000", "HB2.000"]
    assert len(load_index(tmp_path)) == 2  # the rewritten cache is current again: no warning, no rescan


def test_empty_target_type_names_the_file(tmp_path: Path, chip_arrays) -> None:
    write_mstar(tmp_path / "HB1.000", chip_arrays[0], fields={"TargetType": ""})
    with pytest.raises(ValueError, match=r"HB1.000: header field 'TargetType' is empty"):
        load_index(tmp_path)
