"""Guidance graphs (issue 41 item 1): the file format and its refusals, guided distances, the
heuristic channels under guidance, and `none` / unit costs reproducing the unguided world."""

from __future__ import annotations

import heapq
import json
from pathlib import Path

import numpy as np
import pytest

from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.coordination.plan import distance_rankings
from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.grid.guidance import Guidance, GuidanceError
from mapf_fleet.grid.guidance_made import (FEATURES, CostModel, GuidanceSource, features,
                                           highways)
from mapf_fleet.grid.heuristic import DistanceTable, bfs_distances_many, distance_table
from mapf_fleet.grid.instance import generate_instance


def brute_dijkstra(blocked, costs, goal):
    """Least cost from every cell to `goal` (a plain heap Dijkstra over reversed moves)."""
    h, w = blocked.shape
    dist = np.full((h, w), np.inf)
    dist[goal] = 0.0
    heap = [(0.0, goal)]
    while heap:
        d, (r, c) = heapq.heappop(heap)
        if d > dist[r, c]:
            continue
        for a in range(1, 5):  # a move u -> (r, c) with action a comes from u = (r, c) - delta
            ur, uc = r - ACTION_DELTAS[a, 0], c - ACTION_DELTAS[a, 1]
            if 0 <= ur < h and 0 <= uc < w and not blocked[ur, uc]:
                nd = d + costs[ur, uc, a]
                if nd < dist[ur, uc]:
                    dist[ur, uc] = nd
                    heapq.heappush(heap, (nd, (int(ur), int(uc))))
    return np.where(np.isfinite(dist), dist, -1.0)


def test_guided_distances_are_least_path_costs():
    inst = generate_instance(12, 4, 0.25, np.random.default_rng(3))
    rng = np.random.default_rng(0)
    costs = rng.uniform(0.5, 3.0, (12, 12, 5))
    guidance = Guidance.from_costs(inst.grid, costs)
    table = DistanceTable(inst.grid != 0, guidance)
    for goal in inst.goals:
        got = table.many([goal])[0]
        np.testing.assert_allclose(got, brute_dijkstra(inst.grid != 0, guidance.costs,
                                                       tuple(goal)))


def test_unit_costs_and_none_are_the_bfs_tables_exactly():
    inst = generate_instance(16, 6, 0.3, np.random.default_rng(1))
    bfs = bfs_distances_many(inst.grid, inst.goals)
    unit = distance_table(inst.grid, Guidance.unit(inst.grid))
    assert not unit.guided and unit is distance_table(inst.grid)  # the same shared table
    assert np.array_equal(unit.many(inst.goals), bfs)
    assert CostModel.zeros().guidance(inst.grid).is_unit  # theta = 0: no guidance
    assert GuidanceSource.parse("none").for_map(inst.grid) is None


def test_a_unit_guided_shield_moves_as_the_unguided_one():
    """`none` reproduces today's behaviour: a lifelong-style run of the fleet's rule with unit
    guidance makes exactly the moves of the unguided rule."""
    inst = generate_instance(14, 24, 0.2, np.random.default_rng(7))
    a = make_shield("pibt_anchor_swap", inst.grid, inst.goals)
    b = make_shield("pibt_anchor_swap", inst.grid, inst.goals, guidance=Guidance.unit(inst.grid))
    pa = pb = np.asarray(inst.starts)
    for _ in range(30):
        sa = a.step(pa, distance_rankings(a, pa))
        sb = b.step(pb, distance_rankings(b, pb))
        assert np.array_equal(sa.positions, sb.positions)
        pa, pb = sa.positions, sb.positions


def test_guidance_changes_the_rule_and_the_heuristic_channels():
    grid = np.zeros((3, 6), dtype=np.uint8)
    costs = np.ones((3, 6, 5))
    costs[1, :, 4] = 10.0  # moving right along the middle row is dear: go round it
    guidance = Guidance.from_costs(grid, costs)
    table = DistanceTable(grid != 0, guidance)
    dist = table.many([(1, 5)])
    bits = table.bits(dist)[0]
    assert bits[1, 0] & (1 << 3) == 0  # right from (1, 0): not on a least-cost path
    assert bits[1, 0] & 1 or bits[1, 0] & 2  # up or down is
    shield = make_shield("pibt_anchor", grid, [(1, 5)], guidance=guidance)
    ranking = shield.anchored_ranking(0, 1 * 6 + 0).tolist()
    assert ranking[0] in (1, 2) and ranking.index(4) > ranking.index(1)


@pytest.mark.parametrize("mangle, message", [
    (lambda c, o: (c[:, :-1], o), "costs must have shape"),
    (lambda c, o: (np.where(np.arange(5) == 1, -1.0, c), o), "must be > 0"),
    (lambda c, o: (np.where(np.arange(5) == 2, np.nan, c), o), "is NaN"),
    (lambda c, o: (c, o[:-1]), "made for a"),
])
def test_bad_guidance_files_are_refused_in_one_line(tmp_path, mangle, message):
    inst = generate_instance(8, 2, 0.2, np.random.default_rng(0))
    path = tmp_path / "bad.guidance.npz"
    costs, obstacles = mangle(np.ones((8, 8, 5)), inst.grid.astype(np.uint8))
    np.savez(path, costs=costs, obstacles=obstacles, meta=np.array("{}"))
    with pytest.raises(GuidanceError, match=message) as caught:
        Guidance.load(path, inst.grid)
    assert "\n" not in str(caught.value)
    if message != "costs must have shape":
        assert str(path) in str(caught.value)


def test_a_lane_layout_that_cuts_a_cell_off_is_refused():
    grid = np.zeros((1, 4), dtype=np.uint8)  # a corridor: one-way to the right strands cell 3
    costs = np.ones((1, 4, 5))
    costs[0, :, 3] = np.inf  # no moving left anywhere
    with pytest.raises(GuidanceError, match=r"cut cell \(0, \d\) off"):
        Guidance.from_costs(grid, costs)
    ring = np.ones((3, 3), dtype=np.uint8)
    ring[0, :] = ring[2, :] = ring[:, 0] = ring[:, 2] = 0  # a loop round one obstacle
    costs = np.ones((3, 3, 5))
    costs[0, :, 3] = costs[2, :, 4] = costs[:, 0, 2] = costs[:, 2, 1] = np.inf
    Guidance.from_costs(ring, costs)  # one way round the loop: every cell still reaches all


def test_a_guidance_file_round_trips_and_names_its_map(tmp_path):
    inst = generate_instance(10, 3, 0.2, np.random.default_rng(2))
    made = highways(inst.grid)
    path = made.save(tmp_path / "m.guidance.npz")
    back = Guidance.load(path, inst.grid)
    assert np.array_equal(back.costs, made.costs) and back.key == made.key
    assert back.meta["kind"] == "highways"
    other = generate_instance(10, 3, 0.2, np.random.default_rng(5))
    with pytest.raises(GuidanceError, match="made for another map"):
        Guidance.load(path, other.grid)


def test_guidance_values_are_parsed_once_with_one_refusal(tmp_path):
    assert GuidanceSource.parse("highways").kind == "highways"
    with pytest.raises(GuidanceError, match="no such file: nowhere.costmodel.json"):
        GuidanceSource.parse("nowhere.costmodel.json")
    bad = tmp_path / "x.costmodel.json"
    bad.write_text(json.dumps({"features": list(FEATURES), "theta": [0.0]}))
    with pytest.raises(GuidanceError, match="field 'theta'"):
        GuidanceSource.parse(str(bad))
    model = CostModel.from_vector(np.linspace(-0.5, 0.5, len(FEATURES) + 1))
    path = model.save(tmp_path / "m.costmodel.json")
    source = GuidanceSource.parse(str(path))
    assert source.kind == "model" and source.label == "m"
    inst = generate_instance(9, 2, 0.2, np.random.default_rng(4))
    assert np.allclose(source.for_map(inst.grid).costs[~(inst.grid != 0)],
                       model.guidance(inst.grid).costs[~(inst.grid != 0)])


def test_cost_model_features_are_local_and_finite():
    inst = generate_instance(11, 2, 0.3, np.random.default_rng(6))
    f = features(inst.grid)
    assert f.shape == (11, 11, 4, len(FEATURES)) and np.isfinite(f).all()
    g = highways(inst.grid)
    free = ~(inst.grid != 0)
    assert set(np.unique(g.costs[free][:, 1:][np.isfinite(g.costs[free][:, 1:])])) <= {1.0, 2.0}


def test_lifelong_evaluation_with_guidance_none_is_the_unguided_run():
    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, rollout
    from mapf_fleet.evaluation.policies import build_policy, parse_policy, with_conflict_rule

    instances = lifelong_instances("dense", 17, 24, 2, seed=3)
    goals = []
    for guidance in (None, "none", GuidanceSource("model", model=CostModel.zeros())):
        runs = lifelong_runs(instances, 40, "pibt_anchor_swap", 3, guidance=guidance)
        rollout(build_policy(with_conflict_rule(parse_policy("heuristic"), "pibt_anchor_swap")),
                runs, shielded=True)
        goals.append([run.goals_reached for run in runs])
    assert goals[0] == goals[1] == goals[2]


def test_congestion_flow_makes_moving_against_recent_traffic_dear():
    from mapf_fleet.grid.guidance_made import CongestionFlow

    grid = np.zeros((3, 5), dtype=np.uint8)
    flow = CongestionFlow(grid, beta=1.0, decay=1.0, period=2)
    before = np.array([[1, 0], [1, 1]])
    flow.observe(before, before + [0, 1])  # two robots moving right along the middle row
    assert flow.guidance() is None  # between updates
    flow.observe(before + [0, 1], before + [0, 2])
    g = flow.guidance()
    assert g is not None and not g.is_unit
    assert g.costs[1, 2, 3] > 1.0  # left from (1, 2): against two robots' moves
    assert g.costs[1, 1, 4] == 1.0  # right: with the traffic
    assert g.costs[0, 2, 3] == 1.0  # another row: untouched


def test_a_lifelong_run_with_congestion_guidance_updates_its_graph_and_stays_safe():
    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, rollout
    from mapf_fleet.evaluation.policies import build_policy, parse_policy, with_conflict_rule

    instances = lifelong_instances("warehouse", 21, 32, 1, seed=1)
    runs = lifelong_runs(instances, 40, "pibt_anchor_swap", 1, series=("executed",),
                         guidance="congestion")
    assert runs[0].guidance is None and runs[0].flow is not None
    rollout(build_policy(with_conflict_rule(parse_policy("heuristic"), "pibt_anchor_swap")),
            runs, shielded=True)
    assert runs[0].guidance is not None and runs[0].guidance.meta["kind"] == "congestion"
    assert runs[0].recorder.collisions == 0 and runs[0].goals_reached > 0
    # a new graph every 8 ticks: the map keeps the distance tables of the last two only
    from mapf_fleet.grid import heuristic

    kept = [t for t in heuristic._TABLES.values() if t.guided
            and t.guidance.meta.get("kind") == "congestion" and t.shape == runs[0].grid.shape
            and np.array_equal(t.blocked, runs[0].grid)]
    assert len(kept) == heuristic.ONLINE_TABLES


def test_the_fleet_over_ros_takes_online_guidance_and_refuses_what_is_no_guidance():
    from mapf_fleet.fleet import parameters

    check = parameters.GUIDANCE.check
    assert check("highways") and check("none") and check("congestion")
    assert not check("lanes") and not check("nowhere.online.json")


def test_evaluate_lifelong_runs_with_and_without_guidance(tmp_path):
    from mapf_fleet.evaluation.lifelong import main

    common = ["--lifelong", "--steps", "6", "--instances", "1", "--agents", "6", "--quiet"]
    # the default: the fleet's guidance (`FLEET_GUIDANCE`, highways), what `up` runs
    assert main(common + ["--json", str(tmp_path / "a.json")]) == 0
    assert main(common + ["--guidance", "none", "highways", "congestion",
                          "--json", str(tmp_path / "b.json")]) == 0
    rows = json.loads((tmp_path / "b.json").read_text())["results"]
    assert [r["guidance"] for r in rows] == ["none", "highways", "congestion"]
    first = json.loads((tmp_path / "a.json").read_text())["results"][0]
    assert first["guidance"] == "highways" and first["goals"] == rows[1]["goals"]


def test_evaluate_lifelong_on_workers_gives_the_figures_of_one_process(tmp_path):
    """`--workers 2` splits each row's episodes between two processes: the same goals, episode
    by episode, in the same order (each episode keeps its goal stream); --workers 0 is refused."""
    from mapf_fleet.evaluation.lifelong import main

    common = ["--lifelong", "--steps", "24", "--instances", "3", "--agents", "10", "--quiet",
              "--guidance", "none", "congestion", "--kinds", "dense", "--sizes", "17"]
    for out, workers in (("one", "1"), ("two", "2")):
        assert main(common + ["--workers", workers, "--json", str(tmp_path / f"{out}.json")]) == 0
    one, two = (json.loads((tmp_path / f"{n}.json").read_text())["results"] for n in ("one", "two"))
    assert [r["goals"] for r in one] == [r["goals"] for r in two]
    assert len(one) == 2 and all(len(r["goals"]) == 3 and sum(r["goals"]) > 0 for r in one)
    assert main(common + ["--workers", "0"]) == 2


def test_a_checkpoint_is_evaluated_under_the_guidance_it_was_trained_on(tmp_path):
    """One default everywhere: a checkpoint records the guidance its heuristic channels were
    trained on (metadata guidance); `evaluate` without --guidance runs it there, the heuristic
    and a checkpoint that records none of its own under the fleet's (what `up` runs), and the
    paper's rule `revert` unguided (the paper's protocol)."""
    torch = pytest.importorskip("torch")
    from mapf_fleet.coordination.rules import FLEET_GUIDANCE
    from mapf_fleet.evaluation.policies import parse_policy, with_conflict_rule, with_guidance
    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / "g.pt", build_model(ModelConfig.preset("dhc", "small")), {
        "alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {},
        "guidance": "highways"})
    unguided = save_checkpoint(tmp_path / "u.pt", build_model(ModelConfig.preset("dhc", "small")), {
        "alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {},
        "guidance": "none"})
    unrecorded = save_checkpoint(tmp_path / "o.pt", build_model(ModelConfig.preset("dhc", "small")),
                                 {"alpha": 0.0, "curriculum": {}, "learner_steps": 0,
                                  "training_config": {}})
    names = (str(path), str(unguided), str(unrecorded), "heuristic")
    specs = [with_conflict_rule(parse_policy(p), "pibt_anchor_swap") for p in names]
    assert [s.guidance for s in with_guidance(specs, None)] == [
        "highways", "none", FLEET_GUIDANCE, FLEET_GUIDANCE]
    assert [s.guidance for s in with_guidance(specs, ["none"])] == ["none"] * 4
    paper = [with_conflict_rule(parse_policy(p), "revert") for p in names]
    assert [s.guidance for s in with_guidance(paper, None)] == ["highways", "none", "none", "none"]


def _maps_the_fleet_accepts():
    """Maps of every shape the fleet takes: the smallest and odd-sided ones, one-cell corridors
    and dead ends (where lanes could cut a cell off), a map without a free cell, every
    generated kind at odd and even sides, and the shipped real-robot instance."""
    from mapf_fleet.fleet.instances import load_instance_yaml
    from mapf_fleet.grid.maps import GENERATED_KINDS, generate_kind_instance

    maps = {"1x1": np.zeros((1, 1), np.uint8), "1x7": np.zeros((1, 7), np.uint8),
            "6x1": np.zeros((6, 1), np.uint8), "2x3": np.zeros((2, 3), np.uint8),
            "blocked": np.ones((3, 3), np.uint8),
            # a one-cell corridor with a dead-end spur: every move is the only way somewhere
            "corridor": np.array([[0, 0, 0, 0, 0], [1, 1, 0, 1, 1], [1, 1, 0, 1, 1],
                                  [0, 0, 0, 1, 1]], np.uint8)}
    for kind in GENERATED_KINDS:
        for size in (9, 16, 33):
            try:
                inst = generate_kind_instance(kind, size, 2, np.random.default_rng(size))
            except ValueError:
                continue  # a kind without a map of that side
            maps[f"{kind} {size}"] = np.asarray(inst.grid)
    small = load_instance_yaml(Path(__file__).resolve().parents[1] / "config" / "fleet" / "instance_small.yaml")
    maps["instance_small.yaml"] = np.asarray(small.grid)
    return maps


def test_highways_are_a_valid_graph_on_every_map_the_fleet_accepts():
    """The fleet's default guidance (`FLEET_GUIDANCE`) exists for any map: its lanes are soft
    (never forbidden), so it passes the guidance checks on every shape, and from every free
    cell each cell of its region stays reachable at a guided distance between the BFS steps and
    `HIGHWAY_AGAINST` times them."""
    from mapf_fleet.coordination.rules import FLEET_GUIDANCE
    from mapf_fleet.grid.guidance_made import HIGHWAY_AGAINST

    assert FLEET_GUIDANCE == "highways"
    for name, grid in _maps_the_fleet_accepts().items():
        guidance = GuidanceSource.parse(FLEET_GUIDANCE).for_map(grid)
        assert guidance is not None and guidance.shape == grid.shape, name
        free = [tuple(map(int, cell)) for cell in np.argwhere(grid == 0)]
        goals = free[:: max(1, len(free) // 6)]
        if not goals:
            continue
        guided = distance_table(grid, guidance).many(goals)
        bfs = bfs_distances_many(grid, goals)
        reach = bfs >= 0
        assert np.array_equal(guided >= 0, reach), name  # nothing cut off, nothing new
        assert (guided[reach] >= bfs[reach]).all(), name
        assert (guided[reach] <= HIGHWAY_AGAINST * bfs[reach]).all(), name


def test_up_runs_a_checkpoint_under_the_guidance_it_records(tmp_path):
    """`up` without --guidance takes the guidance the checkpoint records, as `evaluate` does (one
    default everywhere), the fleet's where it records none; --guidance overrides it; online
    guidance recorded is run too; a recorded value `up` cannot run (a model file gone) is
    refused in one line naming the file."""
    pytest.importorskip("rclpy")
    pytest.importorskip("torch")
    from mapf_fleet.coordination.rules import FLEET_GUIDANCE
    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig
    from mapf_fleet.ros import launcher

    def saved(name, **extra):
        return str(save_checkpoint(tmp_path / name, build_model(ModelConfig.preset("dhc", "small")),
                                   {"alpha": 0.0, "curriculum": {}, "learner_steps": 0,
                                    "training_config": {}, **extra}))

    def guidance(*argv):
        _, plan, _ = launcher.prepare([*argv, "--num-robots", "4", "--size", "12"])
        return [plan.sim["guidance"]] + sorted({plan.values[n]["guidance"] for n in plan.values})

    unguided, unrecorded = saved("u.pt", guidance="none"), saved("o.pt")
    assert guidance("--checkpoint", unguided) == ["none", "none"]
    assert guidance("--checkpoint", unrecorded) == [FLEET_GUIDANCE, FLEET_GUIDANCE]
    assert guidance("--checkpoint", unguided, "--guidance", "highways") == ["highways"] * 2
    online = saved("c.pt", guidance="congestion")  # online: the fleet follows it too
    assert guidance("--checkpoint", online) == ["congestion", "congestion"]
    gone = saved("g.pt", guidance=str(tmp_path / "gone.online.json"))
    with pytest.raises(launcher.UpError, match=r"g\.pt: its metadata field guidance: must be "):
        guidance("--checkpoint", gone)
