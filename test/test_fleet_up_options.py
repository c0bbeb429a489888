"""`mapf-fleet up`'s options are generated from the parameter tables (fleet.parameters: a
`Param` with an `Option`), resolved once into an immutable `Plan`, each value checked once at the
boundary; `device` and `guidance` are two such parameters (ROS-free, no checkpoint loaded)."""

from __future__ import annotations

from pathlib import Path

import dataclasses

import pytest

from mapf_fleet.fleet import parameters as P
from mapf_fleet.fleet import up_options as U


def _plan(argv, robots=2, ros_argv=()):
    args = U.build_parser().parse_args(list(argv))
    draft = U.plan_parameters(args, list(ros_argv))
    return args, U.plan_policy_parameters(draft, args, list(ros_argv), robots, "model.pt")


def test_every_option_of_the_tables_is_an_up_option_with_its_default():
    parser = U.build_parser()
    shown = " ".join(parser.format_help().split())
    flags = {a.option_strings[0]: a for a in parser._actions if a.option_strings}
    for entry in U.table_options():
        assert entry.option.flag in flags, entry.name
        if entry.option.part:
            continue
        action = flags[entry.option.flag]
        assert action.default is None  # not given: the table, a params file or -p decide
        if entry.param.type in (int, float) and "default" not in (entry.option.help or ""):
            assert f"(default: {entry.param.default})" in " ".join(action.help.split())
    assert "--device {auto,cpu,cuda}" in shown and "--guidance none|highways|congestion|FILE" in shown


def test_adding_a_parameter_is_one_entry_in_the_table(monkeypatch):
    """A new Param with an Option in the simulator's table: `up` offers it, checks it with the
    table's check and hands it to the simulator, with no other edit."""
    new = P.Param(3, "a knob for this test", lambda v: v >= 1, ">= 1",
                  option=P.Option("--test-knob"))
    monkeypatch.setitem(P.SIMULATOR, "test_knob", new)
    _, plan = _plan(["--test-knob", "5"])
    assert plan.sim["test_knob"] == 5 and plan.origin["mapf_simulator"]["test_knob"] == \
        "--test-knob"
    _, plan = _plan([])
    assert plan.sim["test_knob"] == 3
    with pytest.raises(U.UpError, match=r"^--test-knob must be >= 1, got 0$"):
        _plan(["--test-knob", "0"])


def test_the_plan_is_resolved_once_and_immutable():
    _, plan = _plan(["--size", "12"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.params_path = "x.yaml"
    with pytest.raises(TypeError):
        plan.sim["size"] = 3
    with pytest.raises(TypeError):
        plan.values["mapf_simulator"] = {}
    later = plan.with_run_files(record_file="/tmp/r.json", params_path="/tmp/p.yaml")
    assert (later.sim["record_file"], later.params_path) == ("/tmp/r.json", "/tmp/p.yaml")
    assert plan.sim["record_file"] == "" and plan.params_path == ""
    assert later.ros_args()[-2:] == ["--params-file", "/tmp/p.yaml"]


def test_an_option_is_refused_where_it_does_not_apply(tmp_path):
    (tmp_path / "i.yaml").write_text('grid: ["...."]\nstarts: [[0, 0]]\ngoals: [[0, 3]]\n')
    for argv, text in [(["--size", "20", "--instance", str(tmp_path / "i.yaml")],
                        "--size applies to a generated map, not to --instance or --map"),
                       (["--goal-seed", "4"], "--goal-seed applies to --task-source lifelong"),
                       (["--arrival-timeout", "3"], "--arrival-timeout applies to --real-robots"),
                       (["--scen", "x.scen"], "--scen needs --map")]:
        with pytest.raises(U.UpError) as caught:
            _plan(argv)
        assert str(caught.value).startswith(text), (argv, str(caught.value))
    # whether it applies is read from the resolved run: lifelong from a -p rule
    _, plan = _plan(["--goal-seed", "4"], ros_argv=["--ros-args", "-p",
                                                    "task_source:=lifelong"])
    assert plan.sim["goal_seed"] == 4


def test_device_reaches_every_policy_node_and_is_checked():
    _, plan = _plan([])
    assert plan.device == "auto" and plan.values["mapf_policy_1"]["device"] == "auto"
    _, plan = _plan(["--device", "cpu"])
    assert {plan.values[f"mapf_policy_{i}"]["device"] for i in range(2)} == {"cpu"}
    assert "device" not in plan.sim  # the simulator runs no network
    with pytest.raises(U.UpError, match=r"device must be one of auto, cpu, cuda, got 'gpu'"):
        _plan([], ros_argv=["--ros-args", "-p", "device:=gpu"])


def test_guidance_is_the_fleets_by_default_none_or_an_existing_file_and_one_value_for_the_fleet(
        tmp_path):
    from mapf_fleet.coordination.rules import FLEET_GUIDANCE

    _, plan = _plan([])  # the fleet's guidance, what `evaluate` measures by default
    assert plan.guidance == plan.sim["guidance"] == FLEET_GUIDANCE == "highways"
    assert {plan.values[n]["guidance"] for n in plan.values} == {FLEET_GUIDANCE}
    _, plan = _plan(["--guidance", "none"])  # the unguided world, asked for
    assert plan.guidance is None and {plan.values[n]["guidance"] for n in plan.values} == {"none"}
    with pytest.raises(U.UpError) as caught:
        _plan(["--guidance", str(tmp_path / "missing.yaml")])
    assert str(caught.value) == (f"--guidance must be none, highways, congestion, or an "
                                 f"existing *.guidance.npz, *.costmodel.json or *.online.json, "
                                 f"got '{tmp_path / 'missing.yaml'}'")
    # online guidance: the policy processes follow the graph from the fleet's states
    online = str(Path(__file__).resolve().parents[1] / "models" / "guidance"
                 / "online_warehouse_33x33_128.online.json")
    for value in ("congestion", online):
        _, plan = _plan(["--guidance", value])
        assert {plan.values[n]["guidance"] for n in plan.values} == {value}
    _, plan = _plan(["--guidance", "highways"])
    assert plan.guidance == "highways"
    path = tmp_path / "lanes.yaml"
    path.write_text("{}\n")
    _, plan = _plan(["--guidance", str(path)])
    assert plan.guidance == str(path)
    assert {plan.values[n]["guidance"] for n in plan.values} == {str(path)}
    _, plan = _plan([], ros_argv=["--ros-args", "-p", f"guidance:={path}"])
    assert {plan.values[n]["guidance"] for n in plan.values} == {str(path)}
    # the policy nodes follow the simulator's guidance unless set for them, and then must agree
    _, plan = _plan([], ros_argv=["--ros-args", "-p", f"mapf_simulator:guidance:={path}"])
    assert {plan.values[n]["guidance"] for n in plan.values} == {str(path)}
    with pytest.raises(U.UpError, match="^guidance differs between nodes: mapf_simulator"):
        _plan(["--guidance", str(path)],
              ros_argv=["--ros-args", "-p", "mapf_policy_1:guidance:=none"])
    assert P.resolve_guidance("none") is None
