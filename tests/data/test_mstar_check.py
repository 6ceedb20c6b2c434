"""``python -m sar_zero123.data.mstar_check`` on the real MSTAR folder: the paper's split counts, the raw
chip against its JPEG copy, and a refusal of a folder without an index."""

from __future__ import annotations

import pytest

from sar_zero123.data.mstar_check import (
    PAPER_COUNTS,
    check_mstar_data,
    check_raw_vs_jpeg,
    check_splits,
    main,
)


def test_a_folder_without_an_index_is_refused_naming_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=rf"no MSTAR index at {tmp_path / 'index.csv'}; pass --data"):
        check_mstar_data(tmp_path)
    with pytest.raises(FileNotFoundError, match="no MSTAR index"):
        main(["--data", str(tmp_path), "--output", str(tmp_path / "report.json")])
    assert not (tmp_path / "report.json").exists()


@pytest.mark.shared_data
def test_the_extended_and_soc_splits_hold_the_paper_s_counts(mstar_root):
    report = check_splits(mstar_root)
    assert report["num_chips"] == 11451
    for protocol in ("extended", "soc"):
        assert report["protocols"][protocol] == PAPER_COUNTS[protocol]
    for seed in range(5):  # T72 held out: its 5,850 chips are the test split whatever the seed
        counts = report["protocols"][f"ood-T72 (seed {seed})"]
        assert counts["test"] == 5850 and counts["train"] + counts["val"] == 5601


@pytest.mark.shared_data
def test_the_raw_chip_agrees_with_its_jpeg_up_to_compression(mstar_root, tmp_path):
    report = check_raw_vs_jpeg(mstar_root)
    assert report["raw"]["shape"] == report["jpeg_shape"] == [128, 128]
    assert (report["raw"]["target_class"], report["raw"]["serial"]) == ("BMP2", "c21")
    assert report["raw"]["azimuth_deg"] == pytest.approx(13.191422)
    assert report["correlation_normalised_magnitude"] == pytest.approx(0.91746, abs=1e-4)
    assert report["correlation_after_3x3_mean"] == pytest.approx(0.99181, abs=1e-4)
    assert report["argmax_raw"] == report["argmax_jpeg"] == [65, 62]
