"""Bag recipes: topics → sensors and profiles, one chain per sensor, every mistake named by its key path."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadview_noise.bag_recipe import load_bag_recipe, parse_bag_recipe
from roadview_noise.errors import RecipeError

ROOT = Path(__file__).resolve().parents[1]
TOPICS = {"/cam": {"sensor": "camera", "depth_topic": "/depth"}, "/os/points": "lidar",
          "/radar": {"sensor": "radar", "radar_profile": "generic-77ghz"}}


def test_chains_per_sensor_and_per_topic_inputs():
    r = parse_bag_recipe({"seed": 3, "topics": TOPICS, "chains": {"camera": "CNF16", "lidar": "CNF20",
                                                                  "radar": [{"model": "rain.radar"}]},
                          "params": {"wind.camera": {"wind_speed_m_per_s": 3.0}}})
    assert {t: b.recipe.model_ids for t, b in r.topics.items()} == {
        "/cam": ("wind.camera", "rain.camera"), "/os/points": ("alignment.lidar", "fog.lidar"),
        "/radar": ("rain.radar",)}
    assert r.topics["/radar"].recipe.spec.inputs.radar_profile == "generic-77ghz"
    assert r.topics["/os/points"].sequence_id == "os/points" and r.seed == 3
    assert r.topics["/cam"].recipe.step_params[0] == {"wind_speed_m_per_s": 3.0}
    again = parse_bag_recipe(r.resolved_dict())                                   # what run.json keeps, replayable
    assert again.sha256() == r.sha256()
    assert {t: b.recipe.step_params for t, b in again.topics.items()} == \
        {t: b.recipe.step_params for t, b in r.topics.items()}


def test_one_cnf_for_every_sensor_it_has():
    r = parse_bag_recipe({"topics": {"/radar": "radar"}, "cnf": "CNF26"})
    assert r.topics["/radar"].recipe.model_ids == ("fog.radar", "occlusion.radar")
    single = parse_bag_recipe({"topics": {"/a": "lidar", "/b": "lidar"}, "chain": [{"model": "fog.lidar"}]})
    assert single.topics["/a"].recipe is single.topics["/b"].recipe or \
        single.topics["/a"].recipe.model_ids == single.topics["/b"].recipe.model_ids == ("fog.lidar",)


def test_shipped_bag_recipe_loads():
    r = load_bag_recipe(ROOT / "recipes/bag-rehearse.yaml")
    assert sorted(b.sensor for b in r.topics.values()) == ["camera", "lidar", "radar"]


@pytest.mark.parametrize("data, message", [
    ({"topics": {"/c": "camera"}, "chains": {"camera": [{"model": "rain.camra"}]}},
     "r.yaml: chains.camera[0].model: unknown model 'rain.camra' (did you mean 'rain.camera'"),
    ({"topics": {"/c": "camera", "/l": "lidar"}, "cnf": "CNF16"}, "r.yaml: cnf: CNF16 has no lidar variant"),
    ({"topics": {"/c": {"sensor": "camera", "lidar_profile": "x"}}, "cnf": "CNF16"},
     "r.yaml: topics./c.lidar_profile: 'lidar_profile' is not a key of a camera topic"),
    ({"topics": {"/c": {"sensor": "camera", "depht_topic": "x"}}, "cnf": "CNF16"},
     "r.yaml: topics./c.depht_topic: unknown key 'depht_topic' (did you mean 'depth_topic'"),
    ({"topics": {"/c": {"sensor": "sonar"}}, "cnf": "CNF16"}, "r.yaml: topics./c.sensor: Input should be"),
    ({"topics": {"c": "camera"}, "cnf": "CNF16"}, "r.yaml: topics.c: topic names start with '/'"),
    ({"topics": {"/c": "camera"}, "cnf": "CNF20", "sensor": "lidar"},
     "r.yaml: cnf: topics map to camera but the chain acts on lidar"),
    ({"topics": {"/c": "camera"}, "cnf": "CNF16", "params": {"fog.lidar": {}}},
     "r.yaml: params.fog.lidar: 'fog.lidar' acts on lidar, which no topic maps"),
    ({"topics": {"/c": "camera"}, "cnf": "CNF16", "params": {"rain.camera": {"rain_rate": 3}}},
     "r.yaml: params.rain.camera.rain_rate: rain.camera has no parameter 'rain_rate'"),
    ({"topics": {"/c": "camera"}, "cnf": "CNF16", "sede": 3}, "r.yaml: sede: unknown key 'sede' (did you mean 'seed'"),
    ({"topics": {"/c": "camera"}, "cnf": "CNF16", "inputs": {}}, "r.yaml: inputs: not allowed in a bag recipe"),
    ({"topics": {"/c": "camera"}, "cnf": "CNF16", "sweep": {"rain.camera.rain_rate_mm_per_h": [1, 2]}},
     "r.yaml: sweep: not allowed in a bag recipe"),
    ({"topics": {"/c": "camera"}, "chains": {"camera": "CNF16", "radar": "CNF25"}},
     "r.yaml: chains.radar: no topic maps to radar"),
    ({"topics": {"/c": "camera", "/l": "lidar"}, "chains": {"camera": "CNF16"}},
     "r.yaml: chains: topics map to lidar but `chains:` has no lidar chain"),
    ({"topics": {"/c": "camera"}, "chains": {"camera": "CNF16"}, "cnf": "CNF16"},
     "r.yaml: cnf: give `chains:` or `cnf:`, not both"),
    ({"topics": {"/c": {"sensor": "camera", "depth_topic": "/d"}, "/d": "camera"}, "cnf": "CNF16"},
     "r.yaml: topics./c.depth_topic: depth topic '/d' is itself mapped"),
    ({"topics": {}, "cnf": "CNF16"}, "r.yaml: topics: `topics:` maps topic names"),
    ({"topics": {"/c": "camera"}}, "r.yaml: give `chains:` (a CNF or steps per sensor) or `cnf:`"),
])
def test_bad_bag_recipes_name_the_key(data, message):
    with pytest.raises(RecipeError) as exc:
        parse_bag_recipe(data, source="r.yaml")
    assert str(exc.value).startswith(message), str(exc.value)
