"""write_crops: a chip folder as the exact 8-bit centre crops its stages read."""

from __future__ import annotations

import numpy as np
import pytest
from chip_folders import write_png_chip_folder

from sar_zero123.data.crops import write_crops
from sar_zero123.data.datasets import load_chip
from sar_zero123.data.index import load_index


def test_crops_are_the_pixels_the_stages_read_and_keep_every_record(tmp_path):
    source = write_png_chip_folder(tmp_path / "source")
    write_crops(source, tmp_path / "crops", image_size=16)
    before, after = load_index(source), load_index(tmp_path / "crops")
    assert len(after) == len(before) == 12
    for old, new in zip(before, after):
        assert (new.height, new.width) == (16, 16) and new.path.parent == tmp_path / "crops" / "chips"
        keep = ("target_class", "serial", "depression_deg", "azimuth_deg", "target_type", "source")
        assert [getattr(new, k) for k in keep] == [getattr(old, k) for k in keep]
        np.testing.assert_array_equal(load_chip(new.path, 16), load_chip(old.path, 16))  # exact
    with pytest.raises(ValueError, match="already holds files"):
        write_crops(source, tmp_path / "crops", image_size=16)
    # every other chip of each class, serial and depression in azimuth order (serial s0: 7.5 and 247.5 deg)
    sparse = load_index(write_crops(source, tmp_path / "sparse", image_size=16, every=2).parent)
    assert sorted((r.target_class, r.serial, r.depression_deg, r.azimuth_deg) for r in sparse) == sorted(
        (c, s, d, a) for c in "AB" for d in (15.0, 17.0) for s, a in (("s0", 7.5), ("s1", 127.5))
    )
