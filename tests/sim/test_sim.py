"""Tests of the built-in SAR target simulator (``sar_zero123.sim``)."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from sar_zero123.cli import simulate as main
from sar_zero123.sim import (
    INDEX_COLUMNS,
    PIXEL_SPACING_M,
    RESOLUTION_M,
    TARGET_CLASSES,
    PointSpreadFunction,
    Target,
    make_target,
    render_chip,
    render_scene,
    simulate_dataset,
)
from sar_zero123.sim import dataset as dataset_module
from sar_zero123.sim.geometry import GroundGrid, shadow_mask, vehicle_to_ground
from sar_zero123.sim.primitives import Box
from sar_zero123.sim.scatterers import SURFACE, ScattererSet, aspect_gain

QUIET = {"clutter_db": -300.0, "noise_db": -300.0}  # target only, no clutter or noise


def _point_target(u: float, v: float, z: float) -> Target:
    """One isotropic unit scatterer and no solids (no shadow, no occlusion)."""
    scat = ScattererSet.build(np.array([[u, v, z]]), 0.0, 90.0, np.inf, 1e9, 1.0, 0.0, SURFACE)
    return Target("POINT", 0, (), scat, radius_m=1.0)


def _orientation_deg(magnitude: np.ndarray, floor_db: float = -20.0) -> float:
    """Principal-axis angle of the bright pixels, counter-clockwise from the column axis, in (-90, 90]."""
    power = magnitude.astype(np.float64) ** 2
    w = np.where(power >= power.max() * 10 ** (floor_db / 10), power, 0.0)
    rows, cols = np.indices(magnitude.shape)
    x, y = cols, -rows  # y up = far range
    mx, my = (w * x).sum() / w.sum(), (w * y).sum() / w.sum()
    cxx = (w * (x - mx) ** 2).sum()
    cyy = (w * (y - my) ** 2).sum()
    cxy = (w * (x - mx) * (y - my)).sum()
    return float(np.rad2deg(0.5 * np.arctan2(2 * cxy, cxx - cyy)))


# ---------------------------------------------------------------- targets


def test_classes_and_instances():
    assert len(TARGET_CLASSES) >= 6
    assert all(c == c.upper() for c in TARGET_CLASSES)
    a, a_again, b = make_target("TANK", 0), make_target("tank", 0), make_target("TANK", 1)
    np.testing.assert_array_equal(a.scatterers.position, a_again.scatterers.position)
    assert a.primitives == a_again.primitives
    assert a.primitives != b.primitives  # instances differ slightly
    assert (a.serial, b.serial, a.target_type) == ("sim00", "sim01", "tank_sim")
    # classes differ in shape: footprint radius and number of solids
    shapes = {(len(make_target(c).primitives), round(make_target(c).radius_m, 1)) for c in TARGET_CLASSES}
    assert len(shapes) == len(TARGET_CLASSES)


def test_make_target_rejects_bad_input():
    with pytest.raises(ValueError, match="class_name"):
        make_target("HOVERCRAFT")
    with pytest.raises(ValueError, match="instance"):
        make_target("TANK", -1)


def test_aspect_gain_broadside_flash():
    # a face with normal at 90 deg (left side), lobe 3 deg: full gain at broadside, sinc on the
    # main lobe, the 1 / (pi x) sidelobe envelope beyond (no nulls), nothing from behind
    scat = ScattererSet.build(np.zeros((1, 3)), 90.0, 0.0, 3.0, 90.0, 1.0, 0.0, 0)
    gains = [aspect_gain(scat, az, 0.0)[0] for az in (90.0, 90.9, 91.5, 93.0, 120.0, 270.0)]
    expected = [1.0, np.sinc(0.3), 2 / np.pi, 1 / np.pi, 1 / (10 * np.pi), 0.0]
    np.testing.assert_allclose(gains, expected, atol=1e-12)
    assert np.all(np.diff(gains[:5]) < 0)  # decreasing away from broadside


# ---------------------------------------------------------------- imaging geometry


def test_psf_resolution_and_sidelobes():
    psf = PointSpreadFunction.build(256)
    # continuous 1-D response around the peak, offsets in pixels
    d = np.linspace(0.0, 12.0, 4001)
    h = np.abs(np.exp(2j * np.pi * np.outer(d, psf.bins) / 256) @ psf.response) / 256
    assert h[0] == pytest.approx(1.0, abs=1e-9)  # unit scatterer -> unit peak
    width_m = 2 * d[np.argmax(h < 10 ** (-3 / 20))] * PIXEL_SPACING_M
    assert width_m == pytest.approx(1.18 * RESOLUTION_M, rel=0.02)  # Taylor-widened nominal resolution
    first_null = np.argmax(np.diff(h) > 0)
    assert 20 * np.log10(h[first_null:].max()) == pytest.approx(-35.0, abs=1.0)  # Taylor -35 dB


def test_layover_and_range_axis():
    size, dep = 65, 17.0
    center = (size - 1) // 2
    # height h images h sin(psi) closer to the radar (radar at the bottom -> larger row)
    h = 5 * PIXEL_SPACING_M / np.sin(np.deg2rad(dep))
    img = np.abs(
        render_scene(_point_target(0.0, 0.0, h), 0.0, dep, size, np.random.default_rng(0), **QUIET).image
    )
    assert np.unravel_index(img.argmax(), img.shape) == (center + 5, center)
    # a ground point 10 pixels farther in ground range (away from the radar) is 10 rows up
    # at azimuth 0 the nose (+u) points at the radar: u = -y
    y = 10 * PIXEL_SPACING_M / np.cos(np.deg2rad(dep))
    img = np.abs(
        render_scene(_point_target(-y, 0.0, 0.0), 0.0, dep, size, np.random.default_rng(0), **QUIET).image
    )
    assert np.unravel_index(img.argmax(), img.shape) == (center - 10, center)
    # left side (+v) of the vehicle appears at the right of the image at azimuth 0
    img = np.abs(
        render_scene(_point_target(0.0, 2.0, 0.0), 0.0, dep, size, np.random.default_rng(0), **QUIET).image
    )
    assert np.unravel_index(img.argmax(), img.shape) == (center, center + 10)


def test_vehicle_to_ground_rotation():
    nose = np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(vehicle_to_ground(nose, 0.0), [0.0, -1.0, 0.0], atol=1e-12)  # at the radar
    np.testing.assert_allclose(vehicle_to_ground(nose, 90.0), [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(vehicle_to_ground(nose, 180.0), [0.0, 1.0, 0.0], atol=1e-12)


def test_shadow_length_of_a_box():
    size, dep, height = 129, 15.0, 2.0
    box = Box(0.0, 0.0, 2.0, 2.0, 0.0, height)
    grid = GroundGrid(size, PIXEL_SPACING_M, dep)
    upper, lower = grid.bounds([box], 0.0, radius_m=1.5)
    shadow = shadow_mask(grid, upper, lower)
    column = shadow[:, (size - 1) // 2][::-1]  # ordered by increasing ground range
    y_hidden = grid.y[column]
    # hidden from the box's near face (y = -1 m) to h / tan(psi) behind its far face (y = +1 m)
    assert y_hidden.min() == pytest.approx(-1.0, abs=grid.dy)
    # within two cells: the footprint's last cell and the shadow's last cell are both on the grid
    assert y_hidden.max() == pytest.approx(1.0 + height / np.tan(np.deg2rad(dep)), abs=2 * grid.dy)
    assert column.sum() == pytest.approx((2.0 + height / np.tan(np.deg2rad(dep))) / grid.dy, abs=1.5)
    # nothing beside the box
    assert not shadow[:, : (size - 1) // 2 - 6].any()


# ---------------------------------------------------------------- clutter statistics


def test_clutter_amplitude_is_rayleigh():
    scene = render_scene(None, 0.0, 17.0, 128, np.random.default_rng(3), clutter_db=-30.0, noise_db=-45.0)
    amp = np.abs(scene.image)
    # Rayleigh: mean / std = sqrt(pi / (4 - pi)) = 1.9131
    assert amp.mean() / amp.std() == pytest.approx(np.sqrt(np.pi / (4 - np.pi)), rel=0.03)
    # mean power = clutter + noise power (the PSF scaling is calibrated)
    assert np.mean(amp**2) == pytest.approx(10**-3.0 + 10**-4.5, rel=0.05)
    # KS test against Rayleigh with the fitted scale, on pixels 3 apart (speckle is correlated)
    sample = amp[::3, ::3].ravel()
    sigma = np.sqrt(np.mean(sample**2) / 2)
    assert stats.kstest(sample, stats.rayleigh(scale=sigma).cdf).pvalue > 0.01
    # a uniform amplitude is rejected by the same test (the test can fail)
    assert stats.kstest(sample, stats.uniform(0, sample.max()).cdf).pvalue < 1e-6


def test_shadow_keeps_only_receiver_noise():
    # the solids of a tank without its scatterers: what remains in the shadow is receiver noise
    tank = make_target("TANK")
    solids_only = dataclasses.replace(tank, scatterers=tank.scatterers.subset(np.zeros(0, dtype=np.int64)))
    scene = render_scene(
        solids_only, 0.0, 17.0, 128, np.random.default_rng(0), clutter_db=-32.0, noise_db=-45.0
    )
    power = np.abs(scene.image) ** 2
    inner = scene.shadow.copy()
    for axis in (0, 1):  # stay 3 pixels inside the shadow edge (PSF leakage)
        for shift in (-3, 3):
            inner &= np.roll(scene.shadow, shift, axis=axis)
    assert inner.sum() > 300
    assert 10 * np.log10(power[inner].mean()) == pytest.approx(-45.0, abs=1.5)
    assert 10 * np.log10(power[~scene.shadow].mean()) == pytest.approx(-32.0, abs=1.0)


# ---------------------------------------------------------------- pose consistency


@pytest.mark.parametrize("class_name", ["TANK", "TRUCK", "SPG"])
def test_dominant_axis_turns_with_azimuth(class_name):
    target = make_target(class_name, 1)
    rng = np.random.default_rng(0)
    for az in (30.0, 60.0, 120.0, 150.0):
        angle = _orientation_deg(render_chip(target, az, 17.0, 128, rng, **QUIET))
        expected = 90.0 - az  # long axis along (sin az, cos az) in (cross-range, far range)
        assert abs((angle - expected + 90.0) % 180.0 - 90.0) < 20.0, (az, angle)


@pytest.mark.parametrize("class_name", ["APC", "TRUCK", "SCOUT"])
def test_broadside_flash(class_name):
    target = make_target(class_name)

    def peak(az: float) -> float:
        return float(
            np.abs(render_scene(target, az, 17.0, 128, np.random.default_rng(0), **QUIET).image).max()
        )

    # the side faces' dihedrals light up within the ~3 deg aperture lobe (measured 2.0-3.2x)
    assert peak(90.0) > 1.5 * max(peak(85.0), peak(95.0))


def test_opposite_azimuths_differ():
    target = make_target("TANK")
    rng = np.random.default_rng(0)
    a, a_again, b = (render_chip(target, az, 17.0, 128, rng, **QUIET) for az in (30.0, 30.0, 210.0))
    np.testing.assert_allclose(a, a_again, atol=1e-9)  # the target alone is deterministic

    def corr(x, y):
        return float(np.corrcoef(x.ravel(), y.ravel())[0, 1])

    assert corr(a, b) < 0.7  # measured 0.57; 1 deg apart: 0.91
    assert corr(a, render_chip(target, 31.0, 17.0, 128, rng, **QUIET)) > corr(a, b)


@pytest.mark.parametrize("az", [0.0, 45.0, 90.0, 270.0])
def test_shadow_on_far_side(az):
    chip = render_chip(make_target("APC"), az, 17.0, 128, np.random.default_rng(1))
    power = chip.astype(np.float64) ** 2
    cols = slice(58, 70)
    # 20-40 pixels (4-8 m) from the centre, beyond the hull: behind = far range (top), in front =
    # near range (bottom, radar side). Medians, so the range sidelobes of a flash (one or two
    # columns) do not count; measured 6.8-9.3 dB.
    behind = np.median(power[24:44, cols])
    in_front = np.median(power[84:104, cols])
    assert 10 * np.log10(in_front / behind) > 5.0


# ---------------------------------------------------------------- chips and normalisation


def test_render_chip_range_and_normalisation():
    target = make_target("SCOUT")
    peak = render_chip(target, 10.0, 15.0, 64, np.random.default_rng(5))
    assert peak.dtype == np.float32 and peak.shape == (64, 64)
    assert peak.max() == 1.0 and peak.min() >= 0.0
    cal = render_chip(
        target, 10.0, 15.0, 64, np.random.default_rng(5), normalization="calibrated", calibration=50.0
    )
    assert 0.0 < cal.max() < 1.0  # nothing reaches 50
    # the calibrated chip is the peak chip times one constant
    ratio = cal[peak > 0.01] / peak[peak > 0.01]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-4)
    with pytest.raises(ValueError, match="normalization"):
        render_chip(target, 10.0, 15.0, 64, normalization="max")
    with pytest.raises(ValueError, match="depression_deg"):
        render_chip(target, 10.0, 95.0, 64)
    with pytest.raises(ValueError, match="azimuth_deg"):
        render_chip(target, float("nan"), 15.0, 64)


def test_render_chip_determinism():
    target = make_target("TRUCK")
    a = render_chip(target, 33.0, 17.0, 64, np.random.default_rng(7))
    b = render_chip(target, 33.0, 17.0, 64, np.random.default_rng(7))
    c = render_chip(target, 33.0, 17.0, 64, np.random.default_rng(8))
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()


# ---------------------------------------------------------------- dataset writer


def _read_index(root: Path) -> list[dict[str, str]]:
    with open(root / "index.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == INDEX_COLUMNS
        return list(reader)


SMALL = {"instances": 1, "azimuth_step_deg": 90.0, "depressions_deg": (15.0, 17.0), "size": 32}


def test_simulate_dataset_layout_and_determinism(tmp_path):
    a = simulate_dataset(tmp_path / "a", classes=["TANK", "DOZER"], seed=1, **SMALL)
    b = simulate_dataset(tmp_path / "b", classes=["TANK", "DOZER"], seed=1, **SMALL)
    c = simulate_dataset(tmp_path / "c", classes=["TANK", "DOZER"], seed=2, **SMALL)
    only_tank = simulate_dataset(tmp_path / "d", classes=["TANK"], seed=1, **SMALL)
    rows = _read_index(a)
    assert len(rows) == 2 * 1 * 2 * 4
    assert rows[0] == {
        "path": "chips/15deg/TANK/TANK_sim00_0000.npy",
        "target_class": "TANK",
        "target_type": "tank_sim",
        "serial": "sim00",
        "depression_deg": "15",
        "azimuth_deg": "0.0000",
        "height": "32",
        "width": "32",
    }
    assert {r["azimuth_deg"] for r in rows} == {"0.0000", "90.0000", "180.0000", "270.0000"}
    assert (a / "index.csv").read_bytes() == (b / "index.csv").read_bytes()
    for r in rows:
        chip = np.load(a / r["path"])
        assert chip.dtype == np.float32 and chip.shape == (32, 32) and chip.max() == 1.0
        assert chip.tobytes() == np.load(b / r["path"]).tobytes()
        assert chip.tobytes() != np.load(c / r["path"]).tobytes()
        if r["target_class"] == "TANK":  # a chip does not depend on the other classes simulated
            assert chip.tobytes() == np.load(only_tank / r["path"]).tobytes()
    assert not list(a.glob(".index-*"))


def test_simulate_dataset_jitter(tmp_path):
    root = simulate_dataset(
        tmp_path,
        classes=["SCOUT"],
        instances=1,
        azimuth_step_deg=30.0,
        depressions_deg=(17.0,),
        size=16,
        azimuth_jitter_deg=10.0,
    )
    az = np.array([float(r["azimuth_deg"]) for r in _read_index(root)])
    grid = np.arange(12) * 30.0
    offset = (az - grid + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(offset) <= 5.0) and np.all((az >= 0) & (az < 360))
    assert np.abs(offset).min() > 0 or np.abs(offset).max() > 0.5  # not all on the grid
    assert len(set(np.round(offset, 4))) == 12


def test_simulate_dataset_interrupted_leaves_no_index(tmp_path, monkeypatch):
    simulate_dataset(
        tmp_path, classes=["TANK"], instances=1, azimuth_step_deg=180.0, depressions_deg=(17.0,), size=16
    )
    assert (tmp_path / "index.csv").exists()
    calls = {"n": 0}
    real = dataset_module.render_chip

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("disk full")
        return real(*args, **kwargs)

    monkeypatch.setattr(dataset_module, "render_chip", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        simulate_dataset(
            tmp_path, classes=["TANK"], instances=1, azimuth_step_deg=90.0, depressions_deg=(17.0,), size=16
        )
    assert not (tmp_path / "index.csv").exists()  # the stale index was removed, no partial one written
    assert not list(tmp_path.glob(".index-*"))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"classes": ["HOVERCRAFT"]}, "classes"),
        ({"instances": 0}, "instances"),
        ({"azimuth_step_deg": 0.0}, "azimuth_step_deg"),
        ({"depressions_deg": (95.0,)}, "depressions_deg"),
        ({"size": 8}, "size"),
        ({"seed": -1}, "seed"),
        ({"azimuth_jitter_deg": 6.0, "azimuth_step_deg": 5.0}, "azimuth_jitter_deg"),
        ({"normalization": "max"}, "normalization"),
        ({"clutter_db_spread": -1.0}, "clutter_db_spread"),
        ({"classes": ["TANK", "tank"]}, r"classes: duplicate names in \['TANK', 'TANK'\]"),
        ({"azimuth_step_deg": 1e-9}, r"azimuth_step_deg=1e-09 .* would write .* chips, more than 200000"),
        ({"size": 100_000}, r"size: expected an integer in \[16, 1024\] \(pixels\), got 100000"),
        ({"size": 1024, "instances": 60, "classes": ["TANK"]}, r"size: 8640 chips of 1024 .* 33.8 GiB"),
    ],
)
def test_simulate_dataset_rejects_bad_arguments(tmp_path, kwargs, field):
    with pytest.raises(ValueError, match=field):
        simulate_dataset(tmp_path, **kwargs)
    assert not (tmp_path / "index.csv").exists()


def test_round_trip_through_load_index(tmp_path):
    data = pytest.importorskip("sar_zero123.data", reason="the data layer has not landed yet")
    if not hasattr(data, "load_index"):
        pytest.skip("sar_zero123.data.load_index has not landed yet")
    root = simulate_dataset(tmp_path, classes=["RADAR"], **SMALL)
    records = data.load_index(root)
    rows = _read_index(root)
    assert len(records) == len(rows) == 8
    for rec, row in zip(records, rows):
        assert rec.path == (root / row["path"]).resolve() or rec.path == root / row["path"]
        assert (rec.target_class, rec.serial, rec.target_type) == ("RADAR", row["serial"], "radar_sim")
        assert rec.depression_deg == float(row["depression_deg"])
        assert rec.azimuth_deg == float(row["azimuth_deg"])
        assert (rec.height, rec.width) == (32, 32)
    if hasattr(data, "load_magnitude"):
        np.testing.assert_array_equal(data.load_magnitude(records[0].path), np.load(root / rows[0]["path"]))


def test_cli_writes_folder_and_contact_sheet(tmp_path, capsys):
    out = tmp_path / "sim"
    argv = f"--out {out} --classes TANK --instances 2 --azimuth_step_deg 120 --depressions_deg 17 --size 32"
    argv += " --contact-sheet"
    assert main(argv.split()).is_dir()
    assert len(_read_index(out)) == 2 * 3
    assert (out / "contact_sheet.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = capsys.readouterr().out.splitlines()
    assert "index.csv: 6 chips" in lines[-1]  # the console script prints the returned folder after it


@pytest.mark.shared_data
def test_contact_sheet_with_real_chips(tmp_path, mstar_root):
    from sar_zero123.sim.contact_sheet import _real_chips, contact_sheet

    rows = _real_chips(mstar_root, ["T62", "NOSUCHCLASS"], (0.0, 90.0), 17.0, 128)
    assert [name for name, _ in rows] == ["T62"]  # absent classes are left out
    (az0, chip0), (az90, chip90) = rows[0][1]
    assert min(az0, 360.0 - az0) < 2.0 and abs(az90 - 90.0) < 2.0  # nearest azimuths
    assert chip0.shape == (128, 128) and chip0.max() <= 1.0
    png = contact_sheet(
        tmp_path / "sheet.png", ["TANK"], (0.0, 90.0), real_root=mstar_root, real_classes=["T62"]
    )
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_refuses_a_folder_holding_another_dataset(tmp_path):
    """The simulate stage never replaces a dataset: other settings are refused, nothing on disk changes."""
    out = tmp_path / "data"
    flags = ["--out", str(out), "--instances", "1", "--azimuth_step_deg", "120", "--size", "16"]
    assert main([*flags, "--classes", "TANK", "APC"]).is_dir()
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert len(before) == 2 * 2 * 3 + 2  # chips, index.csv, run.json
    with pytest.raises(ValueError, match=r"classes: folder \['TANK', 'APC'\], this run \['TANK'\]"):
        main([*flags, "--classes", "TANK"])
    with pytest.raises(ValueError, match="already holds a finished simulate run.*--restart"):
        main([*flags, "--classes", "TANK", "APC"])
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert main([*flags, "--classes", "TANK", "APC", "--resume"]).is_dir()  # finished: kept as it is
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert main([*flags, "--classes", "TANK", "--restart"]).is_dir()
    (moved,) = tmp_path.glob("data.replaced-*")
    assert len((moved / "index.csv").read_text().splitlines()) == 1 + 12
    assert len((out / "index.csv").read_text().splitlines()) == 1 + 6


def test_simulate_config_refuses_a_bad_grid_before_any_work(tmp_path):
    from sar_zero123.stages.simulate import SimulateConfig

    with pytest.raises(ValueError, match="azimuth_step_deg: expected a value in"):
        SimulateConfig(out=str(tmp_path / "x"), azimuth_step_deg=0.0)
    assert not (tmp_path / "x").exists()
