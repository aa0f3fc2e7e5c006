"""Spec parsing: presets are valid, grids enumerate as the paper's Table 2, errors name fields."""

from __future__ import annotations

from pathlib import Path

import pytest

from arpz.config import CeddpConfig, RobotConfig, from_dict
from arpz.experiment.fleet import cell_fleet, start_rate, topic_counts
from arpz.experiment.presets import PRESETS
from arpz.experiment.spec import (
    OPT_DEPTH,
    ExperimentSpec,
    SpecError,
    config_label,
    load_spec,
    normalise_config,
    spec_from_dict,
)


def _spec(**overrides: object) -> ExperimentSpec:
    raw: dict[str, object] = {
        "name": "t",
        "rmax_hz": [100, 1000],
        "depths": [1, 10],
        "configs": ["baseline", "LC+opt"],
    }
    raw.update(overrides)
    return spec_from_dict(raw, source="t.toml")


def test_presets_are_valid_specs() -> None:
    for name, make in PRESETS.items():
        spec = make()
        assert spec.name == name
        assert spec.cells()


def test_paper_machines_covers_table_2() -> None:
    spec = PRESETS["paper-machines"]()
    assert spec.rmax_hz == [100.0, 200.0, 500.0, 1000.0]
    depths = {c.depth for c in spec.cells()}
    assert depths == {1, 5, 10, 100, 1000, 5000, OPT_DEPTH}


def test_cells_give_opt_configs_the_optimiser_depth_only() -> None:
    cells = _spec(repeats=2).cells()
    baseline = [c for c in cells if c.config == "baseline"]
    opt = [c for c in cells if c.config == "lc+opt"]
    assert len(baseline) == 2 * 2 * 2  # rates x depths x repeats
    assert {c.depth for c in opt} == {OPT_DEPTH} and len(opt) == 2 * 2
    assert len({c.key for c in cells}) == len(cells)
    assert cells[0].rmax_hz == 100.0  # Rmax outermost


def test_config_names_normalise() -> None:
    assert normalise_config("OPT+lc") == "lc+opt"
    assert normalise_config("cc+lc+cc") == "lc+cc"
    assert normalise_config("none") == "baseline"
    assert config_label("lc+opt") == "LC + OPT"
    with pytest.raises(ValueError, match="unknown configuration feature 'lcc'"):
        normalise_config("lcc+opt")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"rmax_hz": []}, "rmax_hz"),
        ({"depths": [0]}, "depths must be >= 1"),
        ({"configs": ["baseline", "fast"]}, "unknown configuration feature 'fast'"),
        ({"networks": ["wifi-ugly"]}, "unknown network profile 'wifi-ugly'"),
        ({"repeats": 0}, "repeats"),
        ({"depth": [1]}, "depth"),
        ({"profiles": {"x": {"loss_pct": 120}}}, "loss_pct"),
        ({"profiles": {"x": {"burst_p": 0.1}}}, "burst_r must be > 0"),
    ],
)
def test_errors_name_the_problem(overrides: dict[str, object], message: str) -> None:
    with pytest.raises(SpecError, match=message) as info:
        _spec(**overrides)
    assert str(info.value).startswith("t.toml: ")


def test_custom_profile_and_toml_file(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text(
        'name = "s"\nrmax_hz = [200]\ndepths = [5]\nconfigs = ["cc"]\nnetworks = ["lossy"]\n'
        "[profiles.lossy]\nloss_pct = 20\ndelay_ms = 3\n",
        encoding="utf-8",
    )
    spec = load_spec(path)
    assert spec.profile("lossy").loss_pct == 20
    assert spec.profile("lan").loss_pct == 0
    with pytest.raises(SpecError, match="file not found"):
        load_spec(tmp_path / "missing.toml")
    path.write_text("name = ", encoding="utf-8")
    with pytest.raises(SpecError, match="not valid TOML"):
        load_spec(path)


def test_examples_load() -> None:
    examples = sorted(Path(__file__).parents[3].glob("examples/experiment_*.toml"))
    assert examples
    for path in examples:
        assert load_spec(path).cells()


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_cell_configs_load_as_real_configs(preset: str) -> None:
    """Every config a cell writes is accepted by arpz.config, as the processes will load it."""
    spec = PRESETS[preset]()
    for cell in spec.cells():
        fleet = cell_fleet(
            spec,
            cell,
            listen=["udp/127.0.0.1:7447"],
            robot_connect={r: "udp/127.0.0.1:7450" for r in spec.robot_names},
            rrd="x.rrd",
        )
        ceddp = from_dict(fleet.ceddp, CeddpConfig, source="ceddp")
        assert ceddp.cache_control == ("cc" in cell.config)
        assert ceddp.qos.enabled == ("opt" in cell.config)
        for robot, conf in fleet.robots.items():
            loaded = from_dict(conf, RobotConfig, source=robot)
            assert loaded.local_cache.enabled == ("lc" in cell.config)
            assert loaded.sensor_qos is not None
            assert loaded.sensor_qos.history.name == "KEEP_LAST"
            if cell.depth != OPT_DEPTH:
                assert loaded.sensor_qos.depth == cell.depth
                rate = loaded.sim.beam_rate_hz if loaded.sim else loaded.preset_rate_hz
                assert rate == cell.rmax_hz  # DEADLINE Rmax: every topic at Rmax


def test_opt_cells_start_at_the_optimisers_rate() -> None:
    spec = PRESETS["paper-machines"]()
    assert topic_counts(spec) == [7, 6, 6]
    opt = next(c for c in spec.cells() if c.config == "opt" and c.rmax_hz == 100)
    # eq. 4: R = Rmax / T_avg - Rmin = 100 / (19/3) - 1 (docs/qos-optimiser.md's table)
    assert start_rate(spec, opt) == pytest.approx(281 / 19)
    sim = PRESETS["paper-simulation"]()
    assert topic_counts(sim) == [10, 10, 10]
