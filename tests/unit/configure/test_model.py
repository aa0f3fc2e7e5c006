"""Model files: the issue's example decodes (JSON, TOML); bad files are named and explained."""

from __future__ import annotations

import json

import pytest

from arpz.configure.casestudy import case_study
from arpz.configure.model import ModelError, decode_model, dump_json, dump_toml, load_model

EXAMPLE = {
    "computers": [
        {"name": "robot1", "kind": "robot", "capacity": 100},
        {"name": "server1", "kind": "server", "capacity": 400},
    ],
    "links": [{"between": ["robot1", "server1"], "bandwidth": 54000}],
    "nodes": [
        {
            "name": "amcl1",
            "weight": 0.2,
            "residence": None,
            "coresidence": None,
            "settings": [
                {"cpu": 19, "performance": 20},
                {"cpu": 41, "performance": 50},
                {"cpu": 66, "performance": 100},
            ],
            "continuum": None,
        },
        {"name": "tracker1", "weight": 0.2, "settings": [{"cpu": 80, "performance": 40}]},
        {"name": "environment1", "settings": [{"cpu": 1, "performance": 100}]},
    ],
    "messages": [{"from": "tracker1", "to": "environment1", "bandwidth": 3}],
}

TOML = """
[[computers]]
name = "robot1"
kind = "robot"
capacity = 100

[[computers]]
name = "server1"
kind = "server"
capacity = 400

[[links]]
between = ["robot1", "server1"]
bandwidth = 54000

[[nodes]]
name = "amcl1"
weight = 0.2
continuum = {fit = "poly2", step = 1}
settings = [{cpu = 19, performance = 20}, {cpu = 41, performance = 50},
            {cpu = 66, performance = 100}]

[[nodes]]
name = "nav1"
residence = ["robot1"]
coresidence = "nav"
settings = [{cpu = 25, performance = 10, fixed = true}]

[[messages]]
from = "amcl1"
to = "nav1"
bandwidth = 1
"""


def _with(**changes):
    data = json.loads(json.dumps(EXAMPLE))
    for path, value in changes.items():
        target = data
        keys = path.split(".")
        for key in keys[:-1]:
            target = target[int(key)] if key.isdigit() else target[key]
        last = keys[-1]
        target[int(last) if last.isdigit() else last] = value
    return json.dumps(data)


def test_the_issue_example_decodes():
    model = decode_model(json.dumps(EXAMPLE))
    assert [n.name for n in model.nodes] == ["amcl1", "tracker1", "environment1"]
    assert model.messages[0].source == "tracker1"
    assert model.links[0].between == ("robot1", "server1")


def test_toml_decodes_with_continuum_and_fixed_setting():
    model = decode_model(TOML, fmt="toml")
    assert model.nodes[0].continuum is not None and model.nodes[0].continuum.fit == "poly2"
    assert model.nodes[1].settings[0].fixed
    assert model.nodes[1].coresidence == "nav"


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"links.0.between": ["robot1", "robot9"]}, "unknown computer 'robot9'"),
        ({"nodes.0.residence": ["server7"]}, "unknown computer 'server7'"),
        ({"nodes.0.residence": []}, "residence is an empty list"),
        ({"nodes.0.settings": []}, "settings is empty"),
        ({"computers.0.capacity": -5}, "capacity must not be negative"),
        ({"links.0.bandwidth": -1}, "bandwidth must not be negative"),
        ({"nodes.0.weight": -0.1}, "weight must not be negative"),
        ({"nodes.0.settings.0.cpu": -1}, "cpu must not be negative"),
        ({"nodes.1.name": "amcl1"}, "'amcl1' is used twice"),
        ({"messages.0.to": "ghost"}, "unknown node 'ghost'"),
        ({"nodes.0.continuum": {"fit": "log", "step": 0}}, "step must be a positive"),
    ],
)
def test_bad_models_are_rejected_with_a_message_that_says_where(change, needle):
    with pytest.raises(ModelError) as info:
        decode_model(_with(**change))
    assert needle in str(info.value)


def test_a_coresidence_group_with_conflicting_residences_is_rejected():
    text = _with(
        **{
            "nodes.0.coresidence": "g",
            "nodes.0.residence": ["robot1"],
            "nodes.1.coresidence": "g",
            "nodes.1.residence": ["server1"],
        }
    )
    with pytest.raises(ModelError, match=r"coresidence group 'g'.*none in common"):
        decode_model(text)


def test_unknown_fields_and_wrong_types_are_named():
    with pytest.raises(ModelError, match="capcity"):
        decode_model(_with(**{"computers.0.capcity": 3}))
    with pytest.raises(ModelError, match="kind"):
        decode_model(_with(**{"computers.0.kind": "laptop"}))


def test_all_problems_are_reported_at_once():
    text = _with(**{"computers.0.capacity": -5, "messages.0.to": "ghost"})
    with pytest.raises(ModelError) as info:
        decode_model(text)
    assert "capacity" in str(info.value) and "ghost" in str(info.value)


def test_load_model_names_the_file(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text(_with(**{"nodes.0.settings": []}))
    with pytest.raises(ModelError, match=r"broken\.json"):
        load_model(path)
    missing = tmp_path / "missing.toml"
    with pytest.raises(ModelError, match=r"missing\.toml"):
        load_model(missing)
    bad_toml = tmp_path / "bad.toml"
    bad_toml.write_text("[[computers]\nname=")
    with pytest.raises(ModelError, match=r"bad\.toml"):
        load_model(bad_toml)


def test_json_and_toml_writers_round_trip(tmp_path):
    model = case_study(2, 2, 3)
    (tmp_path / "m.json").write_bytes(dump_json(model))
    (tmp_path / "m.toml").write_text(dump_toml(model))
    assert load_model(tmp_path / "m.json") == model
    assert load_model(tmp_path / "m.toml") == model


def test_case_study_sizes_follow_table_ii():
    for computers, robots, cameras, nodes in [(2, 1, 1, 8), (3, 2, 3, 16)]:
        model = case_study(robots, cameras, computers)
        assert len(model.nodes) == nodes
        assert sum(n.weight for n in model.nodes) == pytest.approx(1.0)
        configurable = [n for n in model.nodes if len(n.settings) > 1]
        assert len(configurable) == cameras + 3 * robots
