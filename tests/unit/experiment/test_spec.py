"""Spec parsing: presets are valid, grids enumerate as the paper's Table 2, errors name fields."""

from __future__ import annotations

from pathlib import Path

import pytest

from arpz.ceddp.optimiser import QosLimits, solve_closed
from arpz.core.config import CeddpConfig, RobotConfig, from_dict
from arpz.experiment.fleet import (
    INITIAL_OPT_DEPTH,
    cell_fleet,
    check_cells,
    configured_qos,
    start_rate,
    topic_counts,
)
from arpz.experiment.presets import PRESETS
from arpz.experiment.spec import (
    OPT_DEPTH,
    Cell,
    ExperimentSpec,
    SpecError,
    config_label,
    load_spec,
    normalise_config,
    opt_depth,
    opt_rate,
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
    assert normalise_config("OptR+LC") == "lc+optr"
    assert normalise_config("optd+cc+lc") == "lc+cc+optd"
    assert config_label("lc+opt") == "LC + OPT"
    assert config_label("lc+optr") == "LC + OPT R-only"
    assert config_label("optd") == "OPT D-only"
    with pytest.raises(ValueError, match="unknown configuration feature 'lcc'"):
        normalise_config("lcc+opt")
    for both in ("opt+optr", "optr+optd", "lc+opt+optd"):
        with pytest.raises(ValueError, match="not several"):
            normalise_config(both)


def test_opt_variants_rate_and_depth() -> None:
    assert [opt_rate(c) for c in ("opt", "lc+optr", "optd", "lc")] == [True, True, False, False]
    assert [opt_depth(c) for c in ("opt", "optr", "lc+optd", "cc")] == [True, False, True, False]


def test_optr_and_optd_cells() -> None:
    """optr runs at every fixed depth, optd (like opt) at the optimiser's depth only."""
    cells = _spec(configs=["optr", "lc+optr", "optd", "lc+cc+optd"], repeats=3).cells()
    for config in ("optr", "lc+optr"):
        mine = [c for c in cells if c.config == config]
        assert {c.depth for c in mine} == {1, 10} and len(mine) == 2 * 2 * 3
    for config in ("optd", "lc+cc+optd"):
        mine = [c for c in cells if c.config == config]
        assert {c.depth for c in mine} == {OPT_DEPTH} and len(mine) == 2 * 3
    # optd alone needs no fixed depth; optr does
    assert _spec(configs=["optd"], depths=[]).cells()
    with pytest.raises(SpecError, match="need at least one fixed depth"):
        _spec(configs=["optr"], depths=[])


def _fleet(spec: ExperimentSpec, cell: Cell) -> tuple[CeddpConfig, list[RobotConfig]]:
    fleet = cell_fleet(
        spec,
        cell,
        listen=["udp/127.0.0.1:7447"],
        robot_connect={r: "udp/127.0.0.1:7450" for r in spec.robot_names},
        rrd="x.rrd",
    )
    robots = [from_dict(c, RobotConfig, source=r) for r, c in fleet.robots.items()]
    return from_dict(fleet.ceddp, CeddpConfig, source="ceddp"), robots


@pytest.mark.parametrize("preset", ["paper-machines", "paper-simulation"])
def test_optr_robots_run_at_the_optimisers_rate_with_the_cells_depth(preset: str) -> None:
    spec = PRESETS[preset]()
    for rmax in spec.rmax_hz:
        best = solve_closed(
            QosLimits(rmax_hz=rmax, rmin_hz=spec.rmin_hz, dmax=spec.dmax), topic_counts(spec)
        )
        for depth in spec.depths:
            ceddp, robots = _fleet(spec, Cell(rmax, depth, "lc+optr", 1, "wifi-bad"))
            assert not ceddp.qos.enabled  # nothing assigned: the robots keep what they start at
            assert ceddp.sensor_qos.depth == depth
            for robot in robots:
                rate = robot.sim.beam_rate_hz if robot.sim else robot.preset_rate_hz
                assert rate == pytest.approx(best.rate_hz) and rate < rmax
                assert robot.sensor_qos is not None and robot.sensor_qos.depth == depth
                assert robot.local_cache.enabled


@pytest.mark.parametrize("preset", ["paper-machines", "paper-simulation"])
def test_optd_robots_run_at_rmax_with_the_optimisers_depth(preset: str) -> None:
    spec = PRESETS[preset]()
    for rmax in spec.rmax_hz:
        best = solve_closed(
            QosLimits(rmax_hz=rmax, rmin_hz=spec.rmin_hz, dmax=spec.dmax), topic_counts(spec)
        )
        ceddp, robots = _fleet(spec, Cell(rmax, OPT_DEPTH, "optd", 1, "wifi-bad"))
        assert not ceddp.qos.enabled
        assert ceddp.sensor_qos.depth == best.depth
        assert best.depth not in (INITIAL_OPT_DEPTH, *spec.depths)  # really the optimiser's
        for robot in robots:
            rate = robot.sim.beam_rate_hz if robot.sim else robot.preset_rate_hz
            assert rate == rmax
            assert robot.sensor_qos is not None and robot.sensor_qos.depth == best.depth
            assert not robot.local_cache.enabled
        assert configured_qos(spec, Cell(rmax, OPT_DEPTH, "optd", 1, "x")) == (rmax, best.depth)


def test_opt_cells_keep_the_ceddps_assignment() -> None:
    spec = PRESETS["paper-machines"]()
    ceddp, robots = _fleet(spec, Cell(100.0, OPT_DEPTH, "opt", 1, "wifi-bad"))
    assert ceddp.qos.enabled and ceddp.qos.rmax_hz == 100.0
    assert all(r.sensor_qos is not None and r.sensor_qos.depth == INITIAL_OPT_DEPTH for r in robots)


def test_infeasible_optimiser_is_a_spec_error_for_optr_and_optd() -> None:
    # Rmax 5 Hz over T_avg 19/3 topics leaves less than Rmin = 1 Hz: no Opt(R), no Opt(D)
    for config in ("optr", "optd"):
        spec = _spec(rmax_hz=[5], configs=[config])
        with pytest.raises(SpecError, match="no Opt"):
            check_cells(spec)
    # OPT itself still runs: the CEDDP reports the optimiser's error and assigns nothing
    spec = _spec(rmax_hz=[5], configs=["opt"])
    check_cells(spec)
    assert start_rate(spec, spec.cells()[0]) == 5.0


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
    """Every config a cell writes is accepted by arpz.core.config, as the processes will load it."""
    spec = PRESETS[preset]()
    for cell in spec.cells():
        fleet = cell_fleet(
            spec,
            cell,
            listen=["udp/127.0.0.1:7447"],
            robot_connect={r: "udp/127.0.0.1:7450" for r in spec.robot_names},
            rrd="x.rrd",
        )
        features = cell.config.split("+")
        ceddp = from_dict(fleet.ceddp, CeddpConfig, source="ceddp")
        assert ceddp.cache_control == ("cc" in features)
        assert ceddp.qos.enabled == ("opt" in features)  # not for optr / optd
        assert ceddp.sensor_qos.depth == configured_qos(spec, cell)[1]
        for robot, conf in fleet.robots.items():
            loaded = from_dict(conf, RobotConfig, source=robot)
            assert loaded.local_cache.enabled == ("lc" in features)
            assert loaded.sensor_qos is not None
            assert loaded.sensor_qos.history.name == "KEEP_LAST"
            rate = loaded.sim.beam_rate_hz if loaded.sim else loaded.preset_rate_hz
            if cell.depth != OPT_DEPTH:
                assert loaded.sensor_qos.depth == cell.depth
            if not opt_rate(cell.config):
                assert rate == cell.rmax_hz  # DEADLINE Rmax: every topic at Rmax
            else:
                assert rate < cell.rmax_hz


def test_opt_cells_start_at_the_optimisers_rate() -> None:
    spec = PRESETS["paper-machines"]()
    assert topic_counts(spec) == [7, 6, 6]
    opt = next(c for c in spec.cells() if c.config == "opt" and c.rmax_hz == 100)
    # eq. 4: R = Rmax / T_avg - Rmin = 100 / (19/3) - 1 (docs/qos-optimiser.md's table)
    assert start_rate(spec, opt) == pytest.approx(281 / 19)
    sim = PRESETS["paper-simulation"]()
    assert topic_counts(sim) == [10, 10, 10]


def test_traffic_reaches_both_sides_configs() -> None:
    spec = _spec(traffic={"plain_downlink": True, "command_qos": {"depth": 1, "lifespan_s": 0.1}})
    check_cells(spec)
    ceddp, robots = _fleet(spec, spec.cells()[0])
    assert ceddp.plain_downlink and ceddp.command_qos.depth == 1
    assert robots and all(r.plain_downlink and r.command_qos.lifespan_s == 0.1 for r in robots)


@pytest.mark.parametrize(
    ("traffic", "message"),
    [
        ({"plain_downlnk": True}, "plain_downlnk"),
        ({"sensor_qos": {"depth": 3}}, "sensor_qos"),
        ({"command_qos": {"depth": 0}}, "command_qos"),
    ],
)
def test_traffic_errors_name_the_key(traffic: dict[str, object], message: str) -> None:
    with pytest.raises(SpecError, match=message):
        check_cells(_spec(traffic=traffic))


def test_lab_networks_name_a_lab_profile_and_a_link() -> None:
    spec = _spec(networks=["lab:wifi-bad", "lab:dead-zone-12s", "wifi-good"], lab_link="quic")
    cells = spec.cells()
    assert {c.network for c in cells} == {"lab:wifi-bad", "lab:dead-zone-12s", "wifi-good"}
    lab_cell = next(c for c in cells if c.network == "lab:dead-zone-12s")
    assert ":" not in lab_cell.slug and "lab-dead-zone-12s" in lab_cell.slug
    with pytest.raises(SpecError, match="network 'lab:wifi-awful'"):
        _spec(networks=["lab:wifi-awful"])
    with pytest.raises(SpecError, match="lab_link must be one of tcp, udp, tls, quic"):
        _spec(networks=["lab:wifi-bad"], lab_link="sctp")
