"""Recipe validation: unknown keys with did-you-mean, value ranges, unknown models, stage order, distributions."""

from __future__ import annotations

import pytest

from roadview_noise.errors import RecipeError
from roadview_noise.recipe import draw_value, parse_recipe
from roadview_noise.seeding import derive_rng

CHAIN = {"chain": [{"model": "compression.camera", "params": {"quality": 15}}], "seed": 1}


def err(data) -> RecipeError:
    with pytest.raises(RecipeError) as e:
        parse_recipe(data, source="r.yaml")
    return e.value


def test_valid_chain_and_cnf():
    r = parse_recipe(CHAIN, source="r.yaml")
    assert r.model_ids == ("compression.camera",) and r.sensor == "camera"
    r = parse_recipe({"cnf": "cnf22"}, source="r.yaml")
    assert r.model_ids == ("power.lidar", "rain.lidar")


def test_unknown_top_level_key_suggests():
    e = err({**CHAIN, "sede": 3})
    assert e.file == "r.yaml" and e.key == "sede" and "'seed'" in str(e)


def test_unknown_nested_key_suggests():
    e = err({**CHAIN, "inputs": {"camra": "*.png"}})
    assert e.key == "inputs.camra" and "'camera'" in str(e)


def test_negative_quality_names_the_key():
    e = err({"chain": [{"model": "compression.camera", "params": {"quality": -5}}]})
    assert e.key == "chain[0].params.quality" and "-5" in str(e)


def test_unknown_model_and_parameter_suggest():
    e = err({"chain": [{"model": "compresion.camera"}]})
    assert "compression.camera" in str(e) and e.key == "chain[0].model"
    e = err({"chain": [{"model": "compression.camera", "params": {"qualty": 10}}]})
    assert "'quality'" in str(e)


def test_unknown_cnf_and_ambiguous_sensor():
    assert "CNF30" in str(err({"cnf": "CNF31"})) or "CNF01" in str(err({"cnf": "CNF31"}))
    e = err({"cnf": "CNF25"})
    assert e.key == "sensor"


def test_physically_impossible_order_refused_unless_as_written():
    chain = [{"model": "rain.lidar"}, {"model": "alignment.lidar"}]
    e = err({"chain": chain})
    assert "alignment.lidar → rain.lidar" in str(e)
    r = parse_recipe({"chain": chain, "order": "as_written"})
    assert r.model_ids == ("rain.lidar", "alignment.lidar")


def test_mixed_sensors_refused():
    assert "one sensor" in str(err({"chain": [{"model": "compression.camera"}, {"model": "rain.lidar"}]}))


def test_distributions_validated_and_drawn_deterministically():
    e = err({"chain": [{"model": "compression.camera", "params": {"quality": {"uniform": [0, 50]}}}]})
    assert "quality" in e.key
    spec = {"uniform": [10, 90]}
    a = [draw_value(spec, derive_rng(3, "f", i)) for i in range(50)]
    b = [draw_value(spec, derive_rng(3, "f", i)) for i in range(50)]
    assert a == b and all(10 <= v <= 90 for v in a) and len(set(a)) == 50
    assert draw_value({"choice": [20, 40]}, derive_rng(1)) in (20, 40)


def test_sweep_gives_one_variant_per_value():
    r = parse_recipe({**CHAIN, "sweep": {"compression.camera.quality": [10, 50, 90]}})
    assert [v.suffix for v in r.variants] == ["__quality-10", "__quality-50", "__quality-90"]
    e = err({**CHAIN, "sweep": {"compression.camera.quality": [0]}})
    assert e.key == "sweep.compression.camera.quality"


def test_a_variant_asked_for_again_is_that_variant():
    """Variants remembers the last variant asked for (a file asks for its own several times): asking in any order
    gives each index its own suffix and values."""
    r = parse_recipe({**CHAIN, "sweep": {"compression.camera.quality": [10, 50, 90]}})
    for i in (2, 2, 1, 0, 0, 2, -1, 1):
        v = r.variants[i]
        assert v.suffix == f"__quality-{(10, 50, 90)[i]}" and v.overrides == {"compression.camera": {"quality":
                                                                                                   (10, 50, 90)[i]}}


def test_params_for_model_not_in_cnf_refused():
    e = err({"cnf": "CNF22", "params": {"fog.lidar": {"visibility_m": 10}}})
    assert e.key == "params.fog.lidar"


def test_cnf_with_a_model_not_built_yet_says_so(monkeypatch):
    import roadview_noise.compound as compound

    known = compound.known
    monkeypatch.setattr(compound, "known", lambda m: m != "ray_drop.lidar" and known(m))
    e = err({"cnf": "CNF28"})
    assert "ray_drop.lidar" in str(e) and "not implemented yet" in str(e)


@pytest.mark.parametrize("glob", ["photos/**/*.JXL", "frames/*.bmp"])
def test_camera_globs_of_photo_formats_not_read_are_refused_at_validate(glob):
    """A phone's HEIC passed validate, then every file failed ("unknown image suffix"). WebP is read (round 22),
    HEIF/HEIC and AVIF with the heif extra (round 23: tests/io/test_heif.py)."""
    with pytest.raises(RecipeError, match=r"camera: .* names \.(jxl|bmp) files, which rvnoise does not read"):
        parse_recipe({"chain": [{"model": "compression.camera"}], "inputs": {"camera": ["**/*.jpg", glob]}})
    parse_recipe({"chain": [{"model": "compression.camera"}], "inputs": {"camera": ["**/*.JPG", "**/*.tif", "**/*",
                                                                                     "**/*.webp"]}})


def test_calibration_from_the_nuscenes_tables_takes_no_label_table():
    """``table: panoptic`` chooses point labels' table; on ``calibration`` it would be ignored in silence."""
    with pytest.raises(RecipeError, match="`table:` chooses the label table"):
        parse_recipe({"chain": [{"model": "fog.camera"}],
                      "inputs": {"camera": "**/*.jpg", "calibration": {"nuscenes": "v1.0-mini", "table": "panoptic"}}})


@pytest.mark.parametrize("sensor, glob, why", [
    ("lidar", "lidar_frontcenter/*.npz", "unknown point-cloud suffix '.npz'"),        # A2D2
    ("lidar", "sensors/lidar/*.parquet", r".*a table is not read: convert it to PCD"),
    ("lidar", "lidar/*.pkl.gz", r".*a pickle is not read .* PandaSet's lidar/NN.pkl.gz"),
    ("lidar", "training/*.tfrecord", r".*Waymo Open Dataset TFRecord .* inputs.bin_fields"),
    ("lidar", "velodyne/*.txt", r".*\(\.txt: radar only\)"),
    ("lidar", "capture/*.pcap", r".*packet capture .* one PCD per scan"),                   # Ouster/Velodyne SDKs
    ("lidar", "maps/*.laz", r".*convert it to PCD or PLY .* empty_rays: ignore"),
    ("radar", "sequence_1/radar_data.h5", "HDF5 is not read: a RadarScenes")])
def test_cloud_globs_of_formats_not_read_are_refused_at_validate(sensor, glob, why):
    """A2D2's .npz, a .parquet table, RadarScenes' .h5 passed validate, then every file failed with the
    reader's refusal; validate now gives it, naming the glob, and for containers users bring (a packet capture, a
    LAZ map) the way to what is read. Globs whose suffix is a wildcard are left to the walk."""
    model = {"lidar": "fog.lidar", "radar": "rain.radar"}[sensor]
    with pytest.raises(RecipeError, match=rf"{sensor}: .* names files rvnoise does not read: {why}"):
        parse_recipe({"chain": [{"model": model}], "inputs": {sensor: ["**/*.pcd", glob]}})
    parse_recipe({"chain": [{"model": model}], "inputs": {sensor: ["**/*.PCD", "**/*.pcd.bin", "**/*", "a/*.p*"]}})


# --- a new user's mistakes (round 22, ux38): each names the key and says what was meant ------------------------------


@pytest.mark.parametrize("cnf", ["cnf5", "CNF5", "cnf 05", 5])
def test_a_cnf_without_its_zero_suggests_that_cnf_only(cnf):
    e = err({"cnf": cnf})
    assert e.key == "cnf" and "(did you mean 'CNF05'?)" in str(e)
    if not isinstance(cnf, str):
        assert "got 5" in str(e)


def test_a_model_without_its_sensor_suggests_every_sensors_model():
    e = err({"chain": [{"model": "fog"}]})
    assert "(did you mean 'fog.camera', 'fog.lidar', 'fog.radar'?)" in str(e)


def test_params_of_a_misspelt_step_suggest_the_step_and_a_real_model_how_to_add_it():
    e = err({"cnf": "CNF05", "params": {"fog.camra": {"visibility_m": 10}}})
    assert e.key == "params.fog.camra" and "(did you mean 'fog.camera'?)" in str(e)
    e = err({"cnf": "CNF05", "params": {"rain.camera": {"rain_rate_mm_per_h": 10}}})
    assert "did you mean" not in str(e) and "`chain:`" in str(e)
    e = err({"chain": [{"model": "fog.camera"}], "params": {"rain.camera": {"rain_rate_mm_per_h": 10}}})
    assert "add rain.camera to `chain:`" in str(e)


@pytest.mark.parametrize("value, says", [
    ("30m", "its unit, m, is part of the name), visibility_m: 30"),
    ("30 m", "visibility_m: 30"),
    ("30", "without quotes, visibility_m: 30"),
    ("30 km", "write the number in m, bare"),
    ("inf", "visibility_m: .inf"),
])
def test_a_number_written_as_text_says_how_to_write_it(value, says):
    e = err({"chain": [{"model": "fog.camera", "params": {"visibility_m": value}}]})
    assert e.key == "chain[0].params.visibility_m" and f"got {value!r}" in str(e) and says in str(e)
    if value == "30 km":
        assert "visibility_m: 30" not in str(e)          # a unit it does not convert is never read as metres


def test_a_model_file_that_does_not_exist_is_refused_at_validate(tmp_path, monkeypatch):
    """README's ray-drop recipe names `model_file: ray_drop.json`; without it every file used to fail one by one."""
    monkeypatch.chdir(tmp_path)
    body = {"cnf": "CNF28", "params": {"ray_drop.lidar": {"backend": "learned", "model_file": "ray_drop.json"}}}
    e = err(body)
    assert e.key == "params.ray_drop.lidar.model_file" and "no file 'ray_drop.json'" in str(e)
    assert str(tmp_path) in str(e)
