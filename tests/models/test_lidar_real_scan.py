"""LiDAR weather on the real Ouster OS1-128 scan in ../shared/data (skipped when absent): continuity at zero
strength, fog returns that spread and fade smoothly with visibility, the intensity kind from Ouster metadata and from
the data, and Hahner's released fog simulation reproduced."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.compound import CNFS, apply_models
from roadview_noise.manifest import read_manifest
from roadview_noise.models.lidar.fog import FogLidar
from roadview_noise.models.lidar.rain import RainLidar
from roadview_noise.models.lidar.snow import SnowLidar
from roadview_noise.physics.lidar_intensity import IntensityWarning
from roadview_noise.profiles.lidar import load_lidar_profile, os1_128_reflectivity
from roadview_noise.provenance import Effect
from roadview_noise.registry import load_all
from roadview_noise.types import PointCloud

#: Hahner's LiDAR_fog_sim (github.com/MartinHahner/LiDAR_fog_sim, commit 1cb9e07) on scan0.bin (N × 4 float32, the
#: 4th column read as intensity): ``fog_simulation.simulate_fog(ParameterSet(alpha=0.1, gamma=1e-6), points, 10)``,
#: as its ``__main__`` calls it, moved 54 818 of the 107 647 points to the fog (``info['num_fog_responses']``) and
#: put none at the origin (measured by running its code locally; none of it is in this repository).
HAHNER_FOG_POINTS = 54_818


def scan(shared_data, profile=None) -> PointCloud:
    a = np.fromfile(shared_data / "os1-128" / "scan0.bin", dtype=np.float32).reshape(-1, 4)
    return PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar",
                      profile or os1_128_reflectivity())


def run(model, cloud, seed=3):
    out, rec = apply_models([model], cloud, seed=seed, key="scan0", sequence_id="s")
    return out, rec[0].diagnostics


def changed(cloud: PointCloud, out: PointCloud) -> int:
    """Points of the input that the output does not hold unchanged, plus the points it adds."""
    n = len(cloud)
    if len(out) < n:
        return n - len(out) + changed(cloud, out)                       # pragma: no cover - only on failure
    same = (np.all(out.positions_m[:n] == cloud.positions_m, axis=1)
            & (out.fields["intensity"][:n] == cloud.fields["intensity"]) & (out.effect[:n] == Effect.KEPT))
    return int(np.count_nonzero(~same)) + len(out) - n


def test_a_trace_of_rain_changes_almost_nothing(shared_data):
    """Rain at 0.001 mm/h changes < 0.1 % of the points: the threshold is calibrated below the scan's weakest returns
    (3 647 lie below the datasheet's 3.28 photons; the sensor detected them), targets keep their recorded value ×
    transmission, the 8-bit readings are stored in whole counts, and new drops add only the detections they cause.
    Snow and fog go to the input as well (snow at 0.001 mm/h is 18 crystals of 18.5 µg per m³, physics/dsd.py, which
    the scan's sensitivity sees within a few metres on 2.4 % of the sky rays: 0.60 % of the points change; 0.0001
    mm/h changes 62 points; tests/physics/test_trace_snow.py)."""
    cloud = scan(shared_data)
    for model in (RainLidar(rain_rate_mm_per_h=0.001), SnowLidar(snowfall_rate_mm_per_h=0.0001),
                  FogLidar(visibility_m=1e7)):
        out, d = run(model, cloud)
        assert changed(cloud, out) < 0.001 * len(cloud), model.id
        assert d["below_threshold_in"] == 3647 and d["removed"] == 0
        assert d["detection_threshold"] < 0.32 and d["detection_threshold_source"].startswith("calibrated")


@pytest.mark.parametrize("cnf", ["CNF19", "CNF20", "CNF21"])
def test_misaligned_chains_keep_the_weather_on_the_empty_rays(shared_data, cnf):
    """CNF19–21 (alignment, then rain / fog / snow) on the scan as a ring-less KITTI-style .bin add weather on its
    23 425 empty rays within 5 % of the same weather without alignment: the rings alignment recovered before tilting
    the beams travel with the points (``attributes['ring']``) and its beam table is the tilted one. Before, the rings
    recovered from the tilted elevations broke the firing grid and 30 m fog added 0 returns to the sky."""
    cloud = scan(shared_data)
    assert "ring" not in cloud.fields
    models = [load_all()[name]() for name in CNFS[cnf].chains["lidar"]]
    out, rec = apply_models(models, cloud, seed=3, key="scan0", sequence_id="s")
    chained, alone = rec[1].diagnostics, run(models[1], cloud)[1]
    assert chained["empty_rays"] == alone["empty_rays"] == 128 * 1024 - len(cloud)
    assert alone["added"] > 5000
    assert chained["added"] == pytest.approx(alone["added"], rel=0.05)


def test_fog_returns_spread_in_range_and_intensity(shared_data):
    """MOR 30 m: the fog returns of the scan are no deterministic shell — their ranges spread by more than 5 cm.
    (Their 8-bit reflectivity, ~0.1, is stored as the OS1's lowest reading 1; the spread of the received signal is
    tested in test_lidar_weather.py with photon counts.)"""
    out, d = run(FogLidar(visibility_m=30.0), scan(shared_data))
    fog = np.isin(out.effect, (Effect.MOVED, Effect.ADDED))
    r = np.linalg.norm(out.positions_m[fog], axis=1)
    assert fog.sum() > 100_000 and np.std(r) > 0.05
    assert np.all(out.fields["intensity"][fog] == 1)


def _weather_returns(cloud, visibilities):
    counts = []
    for v in visibilities:
        d = run(FogLidar(visibility_m=float(v)), cloud)[1]
        counts.append(d["moved"] + d["added"])
    return np.array(counts)


def test_weather_returns_vary_smoothly_with_visibility(shared_data):
    """Over MOR 300–400 m in 1 % steps the number of weather returns never jumps by more than 3 % of the rays; the
    same at 2–6 km, where the sky rays' fog fades for this scan (its threshold is calibrated 11× below the datasheet's:
    fog on 91 % of the sky rays at 2 km, 26 % at 6 km). Before, every sky ray switched off at once between MOR 380
    and 385 m."""
    cloud = scan(shared_data)
    rays = 128 * 1024
    for lo, hi in ((300.0, 400.0), (2000.0, 6000.0)):
        steps = int(math.ceil(math.log(hi / lo) / math.log(1.01)))
        counts = _weather_returns(cloud, lo * 1.01 ** np.arange(steps + 1))
        assert np.max(np.abs(np.diff(counts))) <= 0.03 * rays, (lo, np.max(np.abs(np.diff(counts))))
        if lo > 1000:
            assert counts[0] - counts[-1] > 0.5 * (rays - len(cloud))          # the sky's fog does fade here


def test_ouster_metadata_states_the_reflectivity_channel(shared_data):
    """The scan as reflectivity .bin with the unit's own metadata (udp_profile_lidar RNG15_RFL8_NIR8) gives the same
    decisions as the built-in os1-128-reflectivity."""
    profile = load_lidar_profile(str(shared_data / "os1-128" / "beam_intrinsics.json"))
    assert profile.intensity_kind == "reflectivity" and profile.intensity_unit == "uint8"
    assert "RNG15_RFL8_NIR8" in profile.intensity_source and profile.columns == 1024
    for model in (FogLidar(), RainLidar(), SnowLidar()):
        a, da = run(model, scan(shared_data, profile))
        b, db = run(model, scan(shared_data))
        np.testing.assert_array_equal(a.positions_m, b.positions_m)
        np.testing.assert_array_equal(a.fields["intensity"], b.fields["intensity"])
        np.testing.assert_array_equal(a.effect, b.effect)
        notes = ("intensity_reading", "empty_rays_source")            # the profiles' names and column counts
        assert {k: v for k, v in da.items() if k not in notes} == {k: v for k, v in db.items() if k not in notes}


def test_nothing_stated_reads_the_data_and_says_so(shared_data):
    """Without any profile (the shipped CNF recipes) the default OS1-128 says photons, the data say 8-bit
    range-compensated reflectivity: they are read as such, with a warning (stderr once per process, manifest)."""
    cloud = scan(shared_data, load_lidar_profile(None))
    with pytest.warns(IntensityWarning, match="8-bit range-compensated reflectivity"):
        a, da = run(FogLidar(), cloud)
    b, _ = run(FogLidar(), scan(shared_data))
    np.testing.assert_array_equal(a.effect, b.effect)
    np.testing.assert_array_equal(a.fields["intensity"], b.fields["intensity"])
    assert "8-bit reflectivity read from the data" in da["intensity_reading"] and "lidar_profile" in \
        da["intensity_warning"]


@pytest.mark.slow
def test_shipped_recipe_without_profile_records_the_reading_in_the_manifest(shared_data, tmp_path):
    """``rvnoise augment --recipe recipes/weather-fog-lidar.yaml`` on the scan as a KITTI-style .bin, no profile: the
    warning is issued and the manifest line records the reading and the warning."""
    src = tmp_path / "in" / "lidar" / "seq" / "000000.bin"
    src.parent.mkdir(parents=True)
    shutil.copy(shared_data / "os1-128" / "scan0.bin", src)
    recipe = yaml.safe_load(open("recipes/weather-fog-lidar.yaml"))
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    result = CliRunner().invoke(app, ["augment", "--recipe", str(tmp_path / "r.yaml"), str(tmp_path / "in"),
                                      str(tmp_path / "out"), "--workers", "1", "--quiet"])
    assert result.exit_code == 0, result.output
    warned = [line for line in result.output.splitlines() if "no profile states the intensity unit" in line]
    assert len(warned) == 1 and "IntensityWarning" in warned[0]                 # stderr, once per run
    (line,) = read_manifest(tmp_path / "out" / "manifest.jsonl")
    steps = line["steps"] if "steps" in line else line["chain"]
    diag = steps[0]["diagnostics"]
    assert "reflectivity" in diag["intensity_reading"] and "intensity_warning" in diag


def test_fog_scale_hahner_reproduces_lidar_fog_sim(shared_data):
    """α = 0.1 m⁻¹ (MOR 29.96 m), Hahner's 20 ns pulse: the fraction of points moved to the fog is Hahner's own
    (:data:`HAHNER_FOG_POINTS`) within 20 % (it is within 1 %), and no point is removed; the fog returns of an 8-bit
    scan below one count are stored as the OS1's lowest reading."""
    cloud = scan(shared_data)
    out, d = run(FogLidar(visibility_m=math.log(20) / 0.1, fog_scale="hahner", pulse_width="hahner_20ns"), cloud)
    fraction, hahner = d["moved"] / d["points_in"], HAHNER_FOG_POINTS / len(cloud)
    assert fraction == pytest.approx(hahner, rel=0.2)
    assert fraction == pytest.approx(hahner, rel=0.01)
    assert d["removed"] == d["added"] == 0 and len(out) == len(cloud)
    assert "hahner" in d["empty_rays_source"]
