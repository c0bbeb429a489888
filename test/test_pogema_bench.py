"""The POGEMA benchmark (mapf_fleet/evaluation/pogema_bench.py): its data, its pins, and the claim
it checks (the project's moves inside POGEMA: 0 rule mismatches, 0 POGEMA mismatches), with a
broken shield to show the checks can fail.

pogema comes from scripts/setup.sh (step 3b, <venv>/pogema; CI runs that set-up too). Without it
the tests that drive POGEMA skip, except under CI (CI=true), where they fail: CI must run them.
"""

# The processes these tests start run the POGEMA benchmark (no ROS); an evaluation process sets
# ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST itself should anything in it start ROS.

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapf_fleet.coordination.pibt import ShieldStep
from mapf_fleet.coordination.rules import Rule
from mapf_fleet.evaluation import pogema_bench as pb
from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.grid.guidance_made import GuidanceSource

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pogema():
    """pogema for this module's tests, then gone from the process again: its pydantic 1 (in
    <venv>/pogema) must not be what a later test's Ray imports (Ray refuses pydantic 1)."""
    path, modules = list(sys.path), set(sys.modules)
    try:
        yield pb.import_pogema()
    except pb.PogemaMissing as err:
        if os.environ.get("CI", "").strip().lower() in ("true", "1", "yes"):
            pytest.fail(f"CI=true: scripts/setup.sh installs pogema for CI; {err}")
        pytest.skip(str(err))
    finally:
        sys.path[:] = path
        where = str(pb.pogema_dir())
        for name in set(sys.modules) - modules:
            if (getattr(sys.modules[name], "__file__", None) or "").startswith(where):
                del sys.modules[name]


def _instance(family: str, k: int = 0):
    return pb.FAMILIES[family].instance(pb.load_maps(family), k)


def test_published_constants_are_the_means_of_the_shipped_raw_data():
    published = pb.load_published()
    everything = range(128)
    for mode, family, method, agents, constant in (
            ("lifelong", "random", "RHCR", 64, pb.RHCR_RANDOM_64),
            ("lifelong", "mazes", "RHCR", 64, pb.RHCR_MAZES_64),
            ("lifelong", "random", "Follower", 64, pb.FOLLOWER_RANDOM_64),
            ("lifelong", "random", "MATS-LP", 64, pb.MATS_LP_RANDOM_64),
            ("lifelong", "warehouse", "Follower", 192, pb.FOLLOWER_WAREHOUSE_192),
            ("one_shot", "mazes", "LaCAM", 64, pb.LACAM_MAZES_64_SUCCESS)):
        value, count = pb.published_mean(published, mode, family, method, agents, everything)
        assert count == 128 and round(value, 3) == constant, (mode, family, method, value)
    # the RHCR figures are the same data over the first 32 instances
    value, _ = pb.published_mean(published, "lifelong", "random", "RHCR", 64, range(32))
    assert round(value, 2) == 4.11


def test_the_benchmark_maps_are_the_published_sets():
    for family, sizes in (("random", range(17, 22)), ("mazes", range(17, 22))):
        maps = pb.load_maps(family)
        assert len(maps) == 128
        for name, text in maps.items():
            rows = text.split()
            assert re.fullmatch(rf"validation-{family}-seed-\d{{3}}", name)
            assert len(rows) in sizes and {len(r) for r in rows} <= set(sizes)
    name, text, seed = _instance("warehouse", 5)
    assert (name, seed) == ("wfi_warehouse", 5)
    rows = text.split()
    assert (len(rows), len(rows[0])) == (33, 46)
    readme = (pb.DATA / "README.md").read_text()
    assert "Apache" in readme and "3303133" in readme


def test_requirements_pogema_pins_exactly_and_leaves_the_project_pins_alone():
    pins = {}
    for line in (REPO / "requirements-pogema.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, sep, version = line.partition("==")
            assert sep and re.fullmatch(r"[\w.]+", version), f"not an exact pin: {line}"
            pins[name.lower().replace("_", "-")] = version
    assert pins["pogema"] == pb.POGEMA_VERSION
    project = {line.split("==")[0].lower().replace("_", "-")
               for line in (REPO / "constraints.txt").read_text().splitlines()
               if "==" in line and not line.startswith("#")}
    assert not set(pins) & project, "requirements-pogema.txt would change a project pin"
    # installed apart: nothing of it is importable in the project's own processes
    out = subprocess.run([sys.executable, "-c", "import importlib.util as u; "
                          "print(u.find_spec('pydantic'), u.find_spec('pogema'))"],
                         capture_output=True, text=True, check=True, cwd="/")
    assert out.stdout.split() == ["None", "None"]


@pytest.mark.parametrize("mode,family,agents,guidance", [
    ("lifelong", "random", 64, "none"),
    ("lifelong", "warehouse", 64, "highways"),
    ("one_shot", "mazes", 32, "none"),
])
def test_our_moves_inside_pogema_match_our_rules_and_pogema(pogema, mode, family, agents,
                                                            guidance):
    name, text, seed = _instance(family)
    result = pb.run_episode(pogema, mode, family, name, text, seed, agents,
                            Rule.parse("pibt_anchor_swap"), GuidanceSource.parse(guidance))
    assert result.rule_mismatches == 0 and result.collisions == 0
    assert result.pogema_mismatches == 0
    if mode == "lifelong":
        assert result.steps == pb.FAMILIES[family].lifelong_steps and result.figure > 1.0
    else:
        assert result.figure in (0.0, 1.0) and result.steps <= 128


def test_the_free_flow_bound_caps_every_episode_and_is_met_when_alone(pogema):
    """`free_flow_bound`: POGEMA's own goal sequences walked alone on shortest paths. A lifelong
    episode under the fleet's rule stays at or below it, and with two agents (they rarely
    meet) comes within a few goals of it."""
    from mapf_fleet.coordination.rules import FLEET_RULE

    for family, agents in (("warehouse", 32), ("random", 16), ("random", 2)):
        name, text, seed = _instance(family)
        bound = pb.free_flow_bound(pogema, family, name, text, seed, agents)
        result = pb.run_episode(pogema, "lifelong", family, name, text, seed, agents,
                                Rule.parse(FLEET_RULE), GuidanceSource.parse("none"))
        assert 0 < result.figure <= bound + 1e-9, (family, agents, result.figure, bound)
        if agents == 2:
            steps = pb.FAMILIES[family].lifelong_steps
            assert (bound - result.figure) * steps <= 2, (result.figure, bound)


class _Uncoordinated:
    """A broken arbiter: every agent takes its first-ranked move whatever the others do."""

    def __init__(self, shield):
        self.shield = shield

    def __getattr__(self, name):
        return getattr(self.shield, name)

    def step(self, positions, rankings):
        nxt = np.asarray(positions) + ACTION_DELTAS[np.asarray(rankings)[:, 0]]
        return ShieldStep(nxt, np.asarray(rankings)[:, 0], np.zeros(len(nxt), dtype=bool))


def test_the_checks_catch_moves_that_break_the_rules(pogema, monkeypatch):
    real = pb.make_shield
    monkeypatch.setattr(pb, "make_shield", lambda *a, **k: _Uncoordinated(real(*a, **k)))
    name, text, seed = _instance("random")
    result = pb.run_episode(pogema, "lifelong", "random", name, text, seed, 64,
                            Rule.parse("pibt_anchor_swap"), GuidanceSource.parse("none"))
    assert result.rule_mismatches > 0 and result.collisions > 0
    assert result.pogema_mismatches > 0


def _main(*args, env=None):
    return subprocess.run([sys.executable, "-m", "mapf_fleet.evaluation.pogema_bench", *args],
                          capture_output=True, text=True, env={**os.environ, **(env or {})},
                          cwd=REPO)


def test_without_pogema_one_line_says_how_to_install_it(tmp_path):
    out = _main("--instances", "1", env={"MAPF_FLEET_POGEMA_DIR": str(tmp_path)})
    if out.returncode == 0:
        pytest.skip("pogema is importable from the venv itself")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "scripts/setup.sh" in lines[0] and str(tmp_path) in lines[0]


def test_bad_arguments_are_refused_in_one_line():
    for args, word in ((["--instances", "200"], "128 instances"),
                       (["--conflict-rule", "revert"], "revert"),
                       (["--guidance", "nowhere.costmodel.json"], "nowhere"),
                       (["--checkpoint", "nowhere.pt"], "nowhere.pt"),
                       (["--checkpoint", "lacam"], "planner")):
        out = _main(*args)
        assert out.returncode == 2, args
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and word in lines[0], (args, out.stderr)


def _shield_recorder(monkeypatch):
    """make_shield wrapped: the graphs each episode's shield is handed (`set_guidance`)."""
    real, given = pb.make_shield, []

    def make(*args, **kwargs):
        shield = real(*args, **kwargs)
        own = shield.set_guidance

        def set_guidance(graph):
            given.append(graph)
            own(graph)

        shield.set_guidance = set_guidance
        return shield

    monkeypatch.setattr(pb, "make_shield", make)
    return given


@pytest.mark.parametrize("guidance", ["congestion",
                                      "models/guidance/online_warehouse_33x33_128.online.json"])
def test_online_guidance_is_stepped_inside_pogema(pogema, monkeypatch, guidance):
    """The source's flow observes every tick and hands the shield a new graph every period
    ticks (as FleetRun.advance); the moves still match our rules and POGEMA's."""
    from dataclasses import replace

    monkeypatch.setitem(pb.FAMILIES, "random", replace(pb.FAMILIES["random"], lifelong_steps=40))
    given = _shield_recorder(monkeypatch)
    source = GuidanceSource.parse(guidance if guidance == "congestion" else str(REPO / guidance))
    assert source.online
    period = source.flow(np.zeros((4, 4))).period
    name, text, seed = _instance("random")
    result = pb.run_episode(pogema, "lifelong", "random", name, text, seed, 32,
                            Rule.parse("pibt_anchor_swap"), source)
    assert result.steps == 40
    assert result.rule_mismatches == 0 and result.collisions == 0
    assert result.pogema_mismatches == 0
    assert result.guidance_updates == 40 // period == len(given)
    # graphs of the robots' traffic: they change from update to update
    assert all(g is not None for g in given)
    assert all(not np.array_equal(a.costs, b.costs) for a, b in zip(given, given[1:]))


def _tiny_checkpoint(path, **meta):
    torch = pytest.importorskip("torch")
    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    torch.manual_seed(0)
    return save_checkpoint(path, build_model(ModelConfig.preset("dhc", "small")), {
        "alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {}, **meta})


def test_a_checkpoint_ranks_inside_pogema_on_the_evaluators_observations(pogema, monkeypatch,
                                                                         tmp_path):
    """--checkpoint: the network ranks every tick (its recorded ranking for the rule), from the
    observations observe_runs builds under the episode's current graph (online guidance too)."""
    from dataclasses import replace

    monkeypatch.setitem(pb.FAMILIES, "random", replace(pb.FAMILIES["random"], lifelong_steps=24))
    path = _tiny_checkpoint(tmp_path / "tiny.pt", rankings={"pibt_anchor_swap": "confidence"})
    rule = Rule.parse("pibt_anchor_swap")
    spec = pb.policy_spec(str(path), rule, "cpu")
    assert spec.resolved_ranking == "confidence"
    policy = pb.policy_of(spec)
    ranked, seen = [], []
    rank, observe = policy.rank, pb.observe_runs
    monkeypatch.setattr(policy, "rank", lambda *a: ranked.append(a[2]) or rank(*a))
    monkeypatch.setattr(pb, "observe_runs",
                        lambda runs, obs: seen.append(runs[0].guidance) or observe(runs, obs))
    given = _shield_recorder(monkeypatch)
    name, text, seed = _instance("random")
    result = pb.run_episode(pogema, "lifelong", "random", name, text, seed, 16, rule,
                            GuidanceSource.parse("congestion"), policy=policy)
    assert ranked == list(range(24))
    assert result.rule_mismatches == 0 and result.collisions == 0
    assert result.pogema_mismatches == 0
    # updates after ticks 8, 16 and 24 (the last, after the episode's final tick, unread)
    assert len(given) == 3 and all(any(g is s for s in seen) for g in given[:-1])
    # no policy: plain PIBT, the network is never asked
    pb.run_episode(pogema, "lifelong", "random", name, text, seed, 16, rule,
                   GuidanceSource.parse("none"))
    assert len(ranked) == 24


def test_the_checkpoint_option_writes_its_rows(pogema, tmp_path):
    path = _tiny_checkpoint(tmp_path / "tiny.pt")
    out = _main("--family", "mazes", "--agents", "8", "--instances", "1", "--device", "cpu",
                "--checkpoint", "heuristic", str(path), "--out", str(tmp_path / "rows.json"))
    assert out.returncode == 0, out.stderr
    rows = __import__("json").loads((tmp_path / "rows.json").read_text())["rows"]
    assert [(r["policy"], r["ranking"]) for r in rows] == [
        ("heuristic", "distance"), ("tiny", Rule.parse("pibt_anchor_swap").default_ranking)]
    assert all(r["rule_mismatches"] == r["pogema_mismatches"] == 0 for r in rows)
    assert all(r["cpu_ms_per_tick"] > 0 and r["ms_per_tick"] > 0 for r in rows)


def test_the_default_guidance_is_what_evaluate_and_up_run():
    """No --guidance: each (checkpoint, rule) runs under `PolicySpec.default_guidance`, the
    fleet's guidance for plain PIBT and `default.pt` under the fleet's rule (what `up` runs);
    --guidance replaces it for every row."""
    from mapf_fleet.coordination.rules import FLEET_GUIDANCE
    from mapf_fleet.evaluation.pogema_bench import guidance_sources, policy_spec

    rule = Rule.parse("pibt_anchor_swap")
    specs = {(c, str(rule)): policy_spec(c, rule, "cpu")
             for c in ("heuristic", str(REPO / "models" / "default.pt"))}
    default = guidance_sources(None, specs)
    assert {key: [s.label for s in v] for key, v in default.items()} \
        == {key: [spec.default_guidance] for key, spec in specs.items()}
    assert [s.label for s in default[("heuristic", str(rule))]] == [FLEET_GUIDANCE]
    asked = guidance_sources(["none", "highways"], specs)
    assert all([s.label for s in v] == ["none", "highways"] for v in asked.values())
