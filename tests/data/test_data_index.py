"""Tests for ChipRecord, index.csv reading/writing and its error messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sar_zero123.data import ChipRecord, load_index, write_index

HEADER = "path,target_class,target_type,serial,depression_deg,azimuth_deg,height,width"


def make_folder(
    tmp_path: Path, rows: list[str], header: str = HEADER, files: tuple[str, ...] = ("a.npy", "b.npy")
):
    for name in files:
        np.save(tmp_path / name, np.full((4, 4), 0.5, dtype=np.float32))
    (tmp_path / "index.csv").write_text("\n".join([header, *rows]) + "\n")
    return tmp_path


GOOD_ROWS = ["a.npy,T72,t72_tank,132,17,359.5,4,4", "b.npy,BMP2,,9563,15.0,0,,"]


def test_load_index_reads_rows(tmp_path: Path) -> None:
    records = load_index(make_folder(tmp_path, GOOD_ROWS))
    assert records[0] == ChipRecord(
        path=(tmp_path / "a.npy").resolve(),
        target_class="T72",
        serial="132",
        depression_deg=17.0,
        azimuth_deg=359.5,
        target_type="t72_tank",
        height=4,
        width=4,
    )
    assert records[0].path.is_absolute()
    assert (records[1].target_type, records[1].height, records[1].depression_deg) == (None, None, 15.0)
    assert records[1].object_id == ("BMP2", "9563")


def test_write_index_round_trip(tmp_path: Path) -> None:
    records = load_index(make_folder(tmp_path, GOOD_ROWS))
    (tmp_path / "index.csv").unlink()
    write_index(records, tmp_path)
    assert load_index(tmp_path) == records
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy", "b.npy", "index.csv"]


def test_write_index_rejects_outside_paths(tmp_path: Path) -> None:
    record = ChipRecord(
        path=tmp_path / "x.npy", target_class="A", serial="1", depression_deg=15, azimuth_deg=1
    )
    (tmp_path / "sub").mkdir()
    with pytest.raises(ValueError, match="must lie inside the indexed folder"):
        write_index([record], tmp_path / "sub")
    assert list((tmp_path / "sub").iterdir()) == []


def test_missing_column(tmp_path: Path) -> None:
    header = "path,target_class,serial,depression_deg,height"
    with pytest.raises(ValueError, match=r"index.csv: missing column\(s\) \['azimuth_deg'\]"):
        load_index(make_folder(tmp_path, ["a.npy,T72,132,17,4"], header=header))


def test_unknown_column(tmp_path: Path) -> None:
    header = HEADER + ",elevation"
    with pytest.raises(ValueError, match=r"unknown column\(s\) \['elevation'\]"):
        load_index(make_folder(tmp_path, ["a.npy,T72,t,132,17,3,4,4,9"], header=header))


def test_missing_chip_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"index.csv:3: chip file 'c.npy' does not exist"):
        load_index(make_folder(tmp_path, [GOOD_ROWS[0], "c.npy,T72,,132,17,3,,"]))


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("a.npy,T72,,132,17,360,,", r"index.csv:2: column 'azimuth_deg' must lie in \[0, 360\)"),
        ("a.npy,T72,,132,17,-0.5,,", r"column 'azimuth_deg' must lie in \[0, 360\)"),
        ("a.npy,T72,,132,17,nan,,", "column 'azimuth_deg' must be finite"),
        ("a.npy,T72,,132,high,3,,", "column 'depression_deg' must be a number, got 'high'"),
        ("a.npy,T72,,132,17,3,4.5,", "column 'height' must be an integer"),
        ("a.npy,T72,,132,17,3_0,,", "column 'azimuth_deg' must be a number, got '3_0'"),  # not 30
        ("a.npy,T72,,132,17,30,6_4,", "column 'height' must be an integer, got '6_4'"),
        ("a.npy,T72,,132,17,3", "expected 8 fields"),
    ],
)
def test_bad_values(tmp_path: Path, row: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        load_index(make_folder(tmp_path, [row]))


def test_empty_index_and_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="lists no chips"):
        load_index(make_folder(tmp_path, []))
    with pytest.raises(FileNotFoundError, match="data folder not found"):
        load_index(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no 'index.csv' and no original MSTAR files"):
        load_index(tmp_path / "empty")
    assert list((tmp_path / "empty").iterdir()) == []


def test_chip_record_coerces_types() -> None:
    record = ChipRecord(path="/x/a.npy", target_class="A", serial="1", depression_deg=15, azimuth_deg=3)
    assert record.path == Path("/x/a.npy") and isinstance(record.azimuth_deg, float)


def test_chip_record_validates() -> None:
    with pytest.raises(ValueError, match=r"azimuth_deg must lie in \[0, 360\)"):
        ChipRecord(path=Path("/x"), target_class="A", serial="1", depression_deg=15.0, azimuth_deg=360.0)
    with pytest.raises(ValueError, match="target_class must be a non-empty"):
        ChipRecord(path=Path("/x"), target_class="", serial="1", depression_deg=15.0, azimuth_deg=0.0)


@pytest.mark.parametrize(
    ("rows", "error", "match"),
    [
        (["a.npy,T72,,132,17,1,,", "b.npy,T72,,132,17,2,,", "a.npy,T72,,132,17,1,,"], ValueError,
         r"index.csv:4: chip file 'a.npy' is listed twice \(also on line 2\)"),
        (["a.npy,T72,,132,17,1,,", "a.npy,BMP2,,9563,17,1,,"], ValueError,
         r"index.csv:3: chip file 'a.npy' is listed under two classes \('T72' on line 2, 'BMP2' here\)"),
    ],
    ids=["duplicate-row", "one-file-two-classes"],
)  # fmt: skip
def test_duplicate_rows_are_errors_naming_the_lines(tmp_path: Path, rows, error, match) -> None:
    with pytest.raises(error, match=match):
        load_index(make_folder(tmp_path, rows))


def test_utf8_bom_in_index_is_read(tmp_path: Path) -> None:
    make_folder(tmp_path, GOOD_ROWS)
    text = (tmp_path / "index.csv").read_text()
    (tmp_path / "index.csv").write_bytes("\ufeff".encode() + text.encode())
    assert [r.path.name for r in load_index(tmp_path)] == ["a.npy", "b.npy"]


@pytest.mark.parametrize("name", ["../../x", "/abs", "a/b", "..", ".", "a\\b"])
def test_a_class_name_that_is_a_path_is_refused_at_the_index(tmp_path: Path, name: str) -> None:
    """The class names a folder of generated views (augment writes views/<target_class>/): ``../../x`` or an
    absolute path in index.csv would write outside the output folder."""
    with pytest.raises(ValueError, match=r"target_class must be a plain name"):
        load_index(make_folder(tmp_path, [f'a.npy,"{name}",,1,17,0,4,4']))


def _index(*rows: bytes) -> bytes:
    return b"\n".join([HEADER.encode(), *rows]) + b"\n"


@pytest.mark.parametrize(
    ("text", "error", "match"),
    [
        (b"", ValueError, r"index.csv: the file is empty; expected a header line with \['path', "
                          r"'target_class', 'serial', 'depression_deg', 'azimuth_deg'\]$"),
        (b"\n\n", ValueError, r"index.csv: the file is empty"),
        (_index(b"a.npy,T72,,132,17,1,,", b"b.npy,T72,,13\xff2,17,2,,"), ValueError,
         r"index.csv:3: column 'serial' holds the byte 0xff, which is not UTF-8; save the index as UTF-8 "
         r"text$"),
        (b"pa\xe9th" + HEADER[4:].encode() + b"\n", ValueError,
         r"index.csv:1: the header holds the byte 0xe9"),
        (_index(b"../a.npy,T72,,132,17,1,,"), ValueError,
         r"index.csv:2: column 'path' '../a.npy' leads out of the data folder .*; a relative path must "
         r"stay inside it$"),
        (_index(b"sub/../../a.npy,T72,,132,17,1,,"), ValueError,
         r"index.csv:2: column 'path' 'sub/../../a.npy' leads out of the data folder"),
        (_index(b"..,T72,,132,17,1,,"), ValueError, r"index.csv:2: column 'path' '..' leads out"),
        (_index(b",T72,,132,17,1,,"), ValueError,
         r"index.csv:2: column 'path' must name a chip file, got ''$"),
        (_index(b"a\x00.npy,T72,,132,17,1,,"), ValueError,
         r"index.csv:2: column 'path' must name a chip file, got 'a\\x00.npy'$"),
        (_index(b"a.npy,T72,,132,17,1,,", b"sub/../a.npy,T72,,132,17,1,,"), ValueError,
         r"index.csv:3: chip file 'sub/../a.npy' is listed twice \(also on line 2\)"),
        (_index(b"a.npy,T72,,132,17,inf,,"), ValueError, r"column 'azimuth_deg' must be finite"),
        (_index(b"a.npy,T72,,132,17,1e999,,"), ValueError, r"column 'azimuth_deg' must be finite"),
        (_index(b"a.npy,T72,,132,17,1e308,,"), ValueError,
         r"index.csv:2: column 'azimuth_deg' must lie in \[0, 360\), got 1e\+308"),
        (_index(b"a.npy,T72,,132,nan,1,,"), ValueError, r"column 'depression_deg' must be finite"),
        (_index(b"a.npy,T72,,132,-1e308,1,,"), ValueError,
         r"index.csv:2: column 'depression_deg' must lie in \(0, 90\) degrees, got -1e\+308"),
        (_index(b"/nonexistent/a.npy,T72,,132,17,1,,"), FileNotFoundError,
         r"index.csv:2: chip file '/nonexistent/a.npy' does not exist"),
    ],
    ids=["empty", "blank-lines", "non-utf8-row", "non-utf8-header", "dotdot", "dotdot-nested", "parent",
         "empty-path", "nul", "dup-normalised", "az-inf", "az-1e999", "az-huge", "dep-nan", "dep-huge",
         "absolute-missing"],
)  # fmt: skip
def test_a_hostile_index_is_refused_in_one_line_naming_the_file_row_and_column(tmp_path, text, error, match):
    make_folder(tmp_path, [])
    (tmp_path / "sub").mkdir()
    (tmp_path / "index.csv").write_bytes(text)
    with pytest.raises(error, match=match) as refused:
        load_index(tmp_path)
    assert "\n" not in str(refused.value)


def test_an_index_reads_inside_its_folder_and_absolute_paths_as_written(tmp_path: Path) -> None:
    """``sub/../a.npy`` stays inside and is ``a.npy``; an absolute path (``augment`` lists the real chips it
    keeps in place so) names its file outright; a byte-order mark is dropped."""
    data, elsewhere = tmp_path / "data", tmp_path / "elsewhere"
    data.mkdir()
    elsewhere.mkdir()
    np.save(elsewhere / "c.npy", np.zeros((4, 4), np.float32))
    make_folder(data, ["sub/../a.npy,T72,,132,17,1,,", f"{elsewhere / 'c.npy'},T72,,132,17,2,,"])
    text = (data / "index.csv").read_bytes()
    (data / "index.csv").write_bytes(b"\xef\xbb\xbf" + text)
    records = load_index(data)
    assert [r.path for r in records] == [(data / "a.npy").resolve(), elsewhere / "c.npy"]
