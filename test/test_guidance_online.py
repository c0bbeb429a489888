"""Online learned guidance (issue 41 item 3): the `.online.json` format and its refusals, costs
from the map and recent traffic, the hand-made graphs as points of the model, the model stepped
inside a lifelong run, and `mapf-fleet guidance optimize --model online` (resume, determinism)."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from mapf_fleet.coordination import rules
from mapf_fleet.grid.guidance import GuidanceError
from mapf_fleet.grid.guidance_made import (FEATURES, LOG_COST_CLIP, CongestionFlow, CostModel,
                                           GuidanceSource, highways)
from mapf_fleet.grid.guidance_online import TRAFFIC, OnlineFlow, OnlineModel
from mapf_fleet.grid.instance import generate_instance


def _grid(seed=3, size=11, density=0.2):
    return generate_instance(size, 2, density, np.random.default_rng(seed)).grid


def _random_model(seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    return OnlineModel.from_vector(rng.normal(0.0, scale, OnlineModel.size()))


def _busy_flow(grid, model, ticks=12, robots=10, seed=1):
    """An OnlineFlow after `ticks` ticks of robots stepping at random (some staying put)."""
    from mapf_fleet.grid.actions import move_targets

    blocked = np.asarray(grid) != 0
    h, w = blocked.shape
    targets = move_targets(blocked)
    rng = np.random.default_rng(seed)
    cells = rng.choice(np.flatnonzero(~blocked.ravel()), robots, replace=False)
    flow = OnlineFlow(grid, model)
    for _ in range(ticks):
        nxt = np.array([rng.choice([t for t in targets[c] if t >= 0]) for c in cells])
        flow.observe(np.stack(np.divmod(cells, w), 1), np.stack(np.divmod(nxt, w), 1))
        cells = nxt
    return flow


# --- the file format ----------------------------------------------------------------------------
@pytest.mark.parametrize("mangle, message", [
    (lambda d: d.update(kind="costmodel"), "field 'kind' must be 'online', got 'costmodel'"),
    (lambda d: d.update(static_features=["bias"]), "field 'static_features' must be"),
    (lambda d: d.update(traffic_features=list(reversed(TRAFFIC))), "field 'traffic_features'"),
    (lambda d: d.update(theta=[0.0] * 3), f"field 'theta' must be {len(FEATURES)} finite numbers"),
    (lambda d: d.update(phi=[float("nan")] * len(TRAFFIC)), "field 'phi' must be"),
    (lambda d: d.update(phi=["1"] * len(TRAFFIC)), "field 'phi' must be"),
    (lambda d: d.update(wait="x"), "field 'wait' must be a finite number, got 'x'"),
    (lambda d: d.update(wait=float("inf")), "field 'wait' must be a finite number, got inf"),
    (lambda d: d.update(decay=0.0), r"field 'decay' must be a number in \(0, 1\], got 0.0"),
    (lambda d: d.update(decay=1.5), "field 'decay'"),
    (lambda d: d.update(period=0), "field 'period' must be an integer >= 1, got 0"),
    (lambda d: d.update(period=2.5), "field 'period' must be an integer >= 1, got 2.5"),
    (lambda d: d.update(meta=[1]), "field 'meta' must be a JSON object"),
])
def test_bad_online_models_are_refused_in_one_line(tmp_path, mangle, message):
    path = _random_model().save(tmp_path / "m.online.json")
    data = json.loads(path.read_text())
    mangle(data)
    path.write_text(json.dumps(data))
    with pytest.raises(GuidanceError, match=message) as info:
        GuidanceSource.parse(str(path))
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_an_unreadable_or_non_object_file_is_refused(tmp_path):
    path = tmp_path / "m.online.json"
    path.write_text("{not json")
    with pytest.raises(GuidanceError, match="cannot read an online model"):
        GuidanceSource.parse(str(path))
    path.write_text("[1, 2]")
    with pytest.raises(GuidanceError, match="a JSON object, got list"):
        GuidanceSource.parse(str(path))


def test_an_online_model_round_trips_and_is_parsed_as_online(tmp_path):
    model = _random_model(seed=5)
    model.meta["family"] = "warehouse"
    path = model.save(tmp_path / "w.online.json")
    source = GuidanceSource.parse(str(path))
    assert source.kind == "online" and source.online and source.label == "w"
    assert np.array_equal(source.model.vector(), model.vector())
    assert (source.model.decay, source.model.period) == (model.decay, model.period)
    grid = _grid()
    assert isinstance(source.flow(grid), OnlineFlow)
    free = ~(grid != 0)
    assert np.array_equal(source.for_map(grid).costs[free], model.guidance(grid).costs[free])


@pytest.mark.parametrize("online", ["congestion", "model"])
def test_a_policy_process_follows_the_runs_online_graph_from_its_states(tmp_path, online):
    """The fleet over ROS takes online guidance: a policy process follows the graph from the
    fleet's states (`FlowFollower`), the one the run steps (`FleetRun.advance`), tick for tick;
    a missed state or a late join leaves it broken (and it says why)."""
    from mapf_fleet.fleet import parameters
    from mapf_fleet.fleet.record import Decisions
    from mapf_fleet.fleet.run import FleetRun
    from mapf_fleet.fleet.tasks import LifelongTasks
    from mapf_fleet.grid.guidance_made import FlowFollower, GuidanceSource

    value = "congestion" if online == "congestion" else \
        str(_random_model(4, scale=2.0).save(tmp_path / "w.online.json"))
    assert parameters.GUIDANCE.check(value)
    source = GuidanceSource.parse(value)
    inst = generate_instance(12, 10, 0.2, 3)
    run = FleetRun(inst.grid, inst.starts, LifelongTasks(grid=inst.grid, seed=3), inst.goals,
                   rule="pibt_anchor_swap", max_steps=40, guidance=source.for_map(inst.grid),
                   flow=source.flow(inst.grid))
    follower, late = FlowFollower(source, inst.grid), FlowFollower(source, inst.grid)
    rng = np.random.default_rng(0)
    updates = 0
    while not run.finished():
        follower.follow(7, run.tick, run.positions)
        if run.tick >= 5:
            late.follow(7, run.tick, run.positions)
        graph = follower.at(run.tick)
        assert graph is run.guidance or (graph is not None and run.guidance is not None
                                         and np.array_equal(graph.costs, run.guidance.costs))
        updates += graph is not follower.at(max(run.tick - 1, 0))
        prefs = np.argsort(rng.random((run.num_robots, 5)), axis=1)
        run.step(Decisions.complete(run.tick, prefs))
    assert updates >= 3 and not follower.broken
    assert "joined at tick 5" in late.broken
    follower.follow(7, run.tick + 2, run.positions)  # a state missed
    assert "missed" in follower.broken


# --- costs -------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_costs_are_positive_finite_bounded_and_validated(seed):
    grid = _grid(seed)
    flow = _busy_flow(grid, _random_model(seed, scale=3.0), ticks=16, seed=seed)
    g = flow.model.costs(flow.blocked, flow._static, flow.traffic())  # Guidance validated them
    free = ~(grid != 0)
    used = g.costs[free][np.isfinite(g.costs[free])]
    assert (used > 0).all() and used.min() >= np.exp(-LOG_COST_CLIP) - 1e-12
    assert used.max() <= np.exp(LOG_COST_CLIP) + 1e-12
    assert np.isfinite(g.costs[free][:, 0]).all()  # every free cell can wait
    assert np.isfinite(flow.traffic()).all() and flow.traffic().any()


def test_with_no_traffic_the_model_is_its_static_part():
    grid = _grid(7)
    model = _random_model(7)
    assert model.phi.any()
    flow = OnlineFlow(grid, model)
    assert not flow.traffic().any()
    static = CostModel(model.theta, model.wait).guidance(grid)
    free = ~(grid != 0)
    assert np.allclose(model.costs(grid, flow._static, flow.traffic()).costs[free],
                       static.costs[free])
    assert np.allclose(model.guidance(grid).costs[free], static.costs[free])
    # after traffic it is not
    busy = _busy_flow(grid, model, ticks=16)
    assert not np.allclose(busy.guidance().costs[free], static.costs[free])


def test_the_hand_made_graphs_are_points_of_the_model():
    grid = _grid(4)
    free = ~(grid != 0)
    assert np.allclose(OnlineModel.preset("highways").guidance(grid).costs[free],
                       highways(grid).costs[free])
    assert OnlineModel.preset("none").guidance(grid).is_unit
    # congestion: the same costs as CongestionFlow after the same ticks
    from mapf_fleet.grid.guidance_made import CONGESTION_PERIOD

    online = _busy_flow(grid, OnlineModel.preset("congestion"), ticks=CONGESTION_PERIOD)
    hand = CongestionFlow(grid)
    hand.flow[:, 1:] = online.flow[:, 1:]  # the same moves (waits live in the unused column)
    hand.ticks = online.ticks
    assert np.allclose(online.guidance().costs[free], hand.guidance().costs[free])


def test_waits_and_moves_are_counted_and_decay():
    grid = np.zeros((3, 4), dtype=np.uint8)
    model = OnlineModel.preset("none")
    flow = OnlineFlow(grid, model)
    before = np.array([[1, 1], [0, 0]])
    flow.observe(before, np.array([[1, 2], [0, 0]]))  # one right, one stays
    assert flow.flow[1 * 4 + 1, 4] == 1.0 and flow.flow[0, 0] == 1.0
    flow.observe(np.array([[1, 2], [0, 0]]), np.array([[1, 2], [0, 0]]))
    assert flow.flow[1 * 4 + 1, 4] == pytest.approx(model.decay)
    assert flow.flow[0, 0] == pytest.approx(1.0 + model.decay)
    g = flow.traffic()
    # the move right from (1, 0) leads into (1, 1), whose outflow is the robot's earlier move
    assert g[1 * 4 + 0, 3, TRAFFIC.index("through_target")] == pytest.approx(np.log1p(model.decay))
    # the move left from (1, 2) runs against it
    assert g[1 * 4 + 2, 2, TRAFFIC.index("flow_back")] == pytest.approx(np.log1p(model.decay))
    assert g[0 * 4 + 1, 2, TRAFFIC.index("wait_target")] == pytest.approx(np.log1p(1 + model.decay))


# --- inside a lifelong run -----------------------------------------------------------------------
def _lifelong_goals(guidance, steps=48, seed=2):
    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, rollout
    from mapf_fleet.evaluation.policies import build_policy, parse_policy, with_conflict_rule

    instances = lifelong_instances("warehouse", 21, 32, 2, seed=seed)
    runs = lifelong_runs(instances, steps, "pibt_anchor_swap", seed, series=(),
                         guidance=guidance)
    rollout(build_policy(with_conflict_rule(parse_policy("heuristic"), "pibt_anchor_swap")),
            runs, shielded=True)
    assert all(run.recorder.collisions == 0 for run in runs)
    return [run.goals_reached for run in runs], runs


def test_online_presets_run_as_the_hand_made_guidance_in_a_lifelong_run(tmp_path):
    for preset, hand in (("congestion", "congestion"), ("highways", "highways")):
        path = OnlineModel.preset(preset).save(tmp_path / f"{preset}.online.json")
        goals, runs = _lifelong_goals(str(path))
        assert goals == _lifelong_goals(hand)[0], preset
        assert isinstance(runs[0].flow, OnlineFlow) and runs[0].guidance.meta["kind"] == "online"


def test_an_online_model_is_deterministic_and_updates_its_graph(tmp_path):
    path = _random_model(3, scale=0.5).save(tmp_path / "r.online.json")
    first, runs = _lifelong_goals(str(path))
    again, _ = _lifelong_goals(str(path))
    assert first == again and sum(first) > 0
    assert runs[0].flow.ticks == 48
    assert runs[0].guidance.key != OnlineModel.load(path).guidance(runs[0].grid).key


# --- the optimiser --------------------------------------------------------------------------------
def _optimize(out, *extra, generations=1):
    from mapf_fleet.evaluation.guidance_opt import main

    return main(["optimize", "--kinds", "warehouse", "--size", "17", "--agents", "12",
                 "--steps", "16", "--episodes", "1", "--popsize", "3", "--held-out", "1",
                 "--sigma", "0.3", "--generations", str(generations), "--out", str(out),
                 *extra])


def test_optimize_online_resumes_and_is_deterministic(tmp_path, capsys):
    assert _optimize(tmp_path / "a", "--model", "online", generations=2) == 0
    assert _optimize(tmp_path / "b", "--model", "online", generations=1) == 0
    assert _optimize(tmp_path / "b", "--model", "online", generations=2) == 0
    assert "resuming" in capsys.readouterr().err
    states = [pickle.loads((tmp_path / d / "state.pkl").read_bytes()) for d in "ab"]
    assert [s["generation"] for s in states] == [2, 2]
    assert states[0]["history"] == states[1]["history"]
    assert np.array_equal(states[0]["optimizer"].mean, states[1]["optimizer"].mean)
    assert states[0]["task"]["model"] == "online" and states[0]["init"] == "both"
    model = OnlineModel.load(tmp_path / "a" / "online_warehouse_17x17_12.online.json")
    assert model.vector().shape == (OnlineModel.size(),)
    assert model.meta["init"] == "both" and set(model.meta["held_out_throughput"]) == {
        "none", "highways", "congestion", "start", "learned"}
    card = (tmp_path / "a" / "online_warehouse_17x17_12.md").read_text()
    assert "contraflow" in card and "the starting point" in card
    # the resumed run's card names the command that finished it (--generations 2, not 1)
    resumed = (tmp_path / "b" / "online_warehouse_17x17_12.md").read_text()
    assert "--generations 2" in resumed and "--generations 1" not in resumed
    # a run of the other model in the same directory is refused
    assert _optimize(tmp_path / "a", "--model", "cost", generations=3) == 2


def test_optimize_starts_from_the_hand_made_point(tmp_path):
    from mapf_fleet.evaluation.guidance_opt import initial_vector

    assert np.array_equal(initial_vector("online", "congestion"),
                          OnlineModel.preset("congestion").vector())
    assert not initial_vector("cost", "none").any()
    assert initial_vector("cost", "highways").shape == (len(FEATURES) + 1,)
    assert _optimize(tmp_path / "c", "--model", "cost", "--init", "congestion") == 2
    assert _optimize(tmp_path / "c", "--model", "online", "--init", "highways",
                     generations=0) == 2  # --generations 0 refused before anything starts


def test_a_cost_model_state_written_before_the_model_axis_resumes(tmp_path):
    assert _optimize(tmp_path, generations=1) == 0
    path = tmp_path / "state.pkl"
    state = pickle.loads(path.read_bytes())
    assert state["task"]["model"] == "cost"
    del state["task"]["model"], state["init"]  # as written before --model existed
    path.write_bytes(pickle.dumps(state))
    assert _optimize(tmp_path, generations=2) == 0
    assert pickle.loads(path.read_bytes())["generation"] == 2


def test_optimize_warm_starts_from_a_learned_model_and_names_it(tmp_path):
    from mapf_fleet.evaluation.guidance_opt import initial_vector

    start = _random_model(5, scale=0.3)
    path = start.save(tmp_path / "prior.online.json")
    assert np.array_equal(initial_vector("online", str(path)), start.vector())
    # a file of the other model, a missing file and a broken one are refused before anything runs
    assert _optimize(tmp_path / "x", "--model", "cost", "--init", str(path)) == 2
    assert _optimize(tmp_path / "x", "--model", "online", "--init",
                     str(tmp_path / "missing.online.json")) == 2
    (tmp_path / "bad.online.json").write_text("{}")
    assert _optimize(tmp_path / "x", "--model", "online", "--init",
                     str(tmp_path / "bad.online.json")) == 2
    assert not (tmp_path / "x" / "state.pkl").exists()
    assert _optimize(tmp_path / "w", "--model", "online", "--init", str(path)) == 0
    state = pickle.loads((tmp_path / "w" / "state.pkl").read_bytes())
    assert state["start"] == start.vector().tolist()
    assert state["task"]["plan"] == [rules.LNS_WINDOW, rules.LNS_ITERATIONS,
                                     rules.LNS_NEIGHBOURHOOD]
    model = OnlineModel.load(tmp_path / "w" / "online_warehouse_17x17_12.online.json")
    assert model.meta["plan"] == state["task"]["plan"]
    # the hand-made highways x congestion is measured beside the learned starting point
    assert set(model.meta["held_out_throughput"]) == {"none", "highways", "congestion", "both",
                                                       "start", "learned"}
    card = (tmp_path / "w" / "online_warehouse_17x17_12.md").read_text()
    assert "the starting point (learned: prior.online.json)" in card
    assert "highways x congestion (hand-made, online)" in card
    assert "over its starting point" in card
    assert f"plan {rules.LNS_WINDOW} ticks ahead" in card


def test_a_run_is_resumed_only_under_the_plan_it_ran(tmp_path, monkeypatch):
    assert _optimize(tmp_path, "--model", "online", generations=1) == 0
    monkeypatch.setattr(rules, "LNS_ITERATIONS", rules.LNS_ITERATIONS // 2)
    assert _optimize(tmp_path, "--model", "online", generations=2) == 2
    assert pickle.loads((tmp_path / "state.pkl").read_bytes())["generation"] == 1


@pytest.mark.slow
def test_optimize_on_rays_pool_is_the_run_in_this_process(tmp_path):
    """The candidates and the held-out rows on Ray's local pool give the in-process figures."""
    for out, workers in (("one", "1"), ("pool", "2")):
        assert _optimize(tmp_path / out, "--model", "online", "--workers", workers,
                         generations=2) == 0
    import ray

    ray.shutdown()
    one, pool = (pickle.loads((tmp_path / d / "state.pkl").read_bytes()) for d in ("one", "pool"))
    assert one["history"] == pool["history"]
    models = [OnlineModel.load(tmp_path / d / "online_warehouse_17x17_12.online.json")
              for d in ("one", "pool")]
    assert models[0].meta["held_out_throughput"] == models[1].meta["held_out_throughput"]


def test_every_shipped_guidance_model_loads_and_has_its_card():
    """models/guidance: each learned model loads (the refusals of a bad file) and its card beside
    it gives the held-out figures its meta records; the hand-made point is the preset `both`."""
    from pathlib import Path

    from mapf_fleet.grid.guidance_made import CostModel

    folder = Path(__file__).resolve().parents[1] / "models" / "guidance"
    learned = sorted(folder.glob("*.online.json")) + sorted(folder.glob("*.costmodel.json"))
    assert len(learned) >= 6
    for path in learned:
        if path.name == "hand_both.online.json":
            assert np.array_equal(OnlineModel.load(path).vector(),
                                  OnlineModel.preset("both").vector())
            continue
        model = (OnlineModel if path.name.endswith(".online.json") else CostModel).load(path)
        card = path.with_name(path.name.split(".")[0] + ".md").read_text()
        rows = model.meta["held_out_throughput"]
        assert f"{rows['learned']:.3f}" in card and f"{rows['none']:.3f}" in card, path.name
