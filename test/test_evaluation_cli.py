"""`mapf-fleet evaluate` and `mapf-fleet render` end to end on tiny subsets."""

import json

import numpy as np
import pytest

from mapf_fleet.cli import main as mapf_fleet
from mapf_fleet.evaluation.policies import parse_policy
from mapf_fleet.evaluation.protocol import InstanceSet, Scenario
from mapf_fleet.evaluation.runner import evaluate, run_decentralized
from mapf_fleet.grid.instance import generate_instance


@pytest.fixture(scope="module")
def small_checkpoint(tmp_path_factory):
    pytest.importorskip("torch")
    from mapf_fleet.evaluation.random_checkpoint import save_random_checkpoint

    return str(save_random_checkpoint(tmp_path_factory.mktemp("ckpt") / "dhc_small.pt", "dhc", "small", seed=1))


def _figures(path):
    """The JSON results without the timings (which differ from run to run)."""
    rows = json.loads(path.read_text())["results"]
    for row in rows:
        row.pop("compute_time_s"), row.pop("plan_time_s")
    return rows


def test_cli_smoke_writes_every_output(tmp_path, small_checkpoint, capsys):
    out = tmp_path / "out"
    code = mapf_fleet([
        "evaluate", "--checkpoint", small_checkpoint, "--sizes", "40", "--agents", "4", "--instances", "3",
        "--conflict-rule", "revert", "--cache-dir", str(tmp_path / "cache"), "--quiet",
        "--json", f"{out}.json", "--csv", f"{out}.csv", "--markdown", f"{out}.md", "--plot", f"{out}.png",
    ])
    assert code == 0
    printed = capsys.readouterr().out
    assert "| Success Rate ↑ | 4 |" in printed and "| Average Time Steps ↓ | 4 |" in printed
    for row in ("| dhc_small |", "| heuristic |", "| LaCAM |"):
        assert row in printed
    report = json.loads((tmp_path / "out.json").read_text())
    assert [r["policy"] for r in report["results"]] == ["dhc_small", "heuristic", "LaCAM"]
    assert all(len(r["episodes"]) == 3 and r["max_steps"] == 256 for r in report["results"])
    lacam = report["results"][2]
    assert lacam["collisions"] == 0 and lacam["success_rate"] == 1.0  # 4 agents on 40x40: easy
    assert lacam["lower_bound_ratio_solved"] >= 1.0
    assert len((tmp_path / "out.csv").read_text().splitlines()) == 4
    assert "Collisions" in (tmp_path / "out.md").read_text()
    assert (tmp_path / "out.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_same_seed_same_table(tmp_path):
    def run(name, seed):
        path = tmp_path / f"{name}.json"
        args = ["evaluate", "--checkpoint", "heuristic", "--no-references", "--sizes", "80", "--agents", "4", "8",
                "--instances", "3", "--seed", str(seed), "--cache-dir", str(tmp_path / name), "--quiet",
                "--json", str(path)]
        assert mapf_fleet(args) == 0
        return _figures(path)

    first, again, other = run("a", 11), run("b", 11), run("c", 12)
    assert first == again
    assert [r["lower_bound"] for r in first] != [r["lower_bound"] for r in other]


def test_movingai_instances_round_trip(tmp_path):
    from mapf_fleet.grid.instance import Instance
    from mapf_fleet.grid.movingai import instance_to_scenario, write_map, write_scen

    base = generate_instance(16, 6, 0.2, np.random.default_rng(4))
    # A second scenario file on the same map, as in the MovingAI benchmark.
    free = np.argwhere(base.grid == 0)
    picks = free[np.random.default_rng(9).choice(len(free), 12, replace=False)]
    second = Instance(base.grid, picks[:6], picks[6:])
    write_map(tmp_path / "m.map", base.grid)
    scen_files = []
    for k, inst in enumerate((base, second)):
        write_scen(tmp_path / f"m-{k}.scen", instance_to_scenario(inst, "m.map"))
        scen_files.append(str(tmp_path / f"m-{k}.scen"))

    path = tmp_path / "mai.json"
    code = mapf_fleet(["evaluate", "--checkpoint", "heuristic", "lacam", "--no-references",
                       "--conflict-rule", "revert", "--map",
                       str(tmp_path / "m.map"), "--scen", *scen_files, "--agents", "6", "--quiet", "--json", str(path)])
    assert code == 0
    via_files = json.loads(path.read_text())["results"]
    assert [r["map"] for r in via_files] == ["m", "m"] and via_files[0]["max_steps"] == 256
    direct = evaluate([parse_policy("heuristic"), parse_policy("lacam", planner_time_limit=2.0)],
                      [(Scenario("m", 6, 256), InstanceSet.from_instances([base, second], "direct"))])
    for from_file, in_memory in zip(via_files, direct):
        assert len(from_file["episodes"]) == 2
        assert from_file["episodes"] == [e.to_dict() for e in in_memory.episodes]


def test_batched_episodes_match_single_episodes(small_checkpoint):
    from mapf_fleet.evaluation.policies import build_policy

    instances = InstanceSet.from_instances(
        [generate_instance(12, 4, 0.2, np.random.default_rng(s)) for s in range(3)], "test")
    policy = build_policy(parse_policy(small_checkpoint))
    together = run_decentralized(policy, instances, 20)
    alone = [run_decentralized(policy, instances.subset(slice(k, k + 1)), 20)[0] for k in range(3)]
    assert together == alone


@pytest.mark.slow
def test_workers_do_not_change_the_results(tmp_path):
    instances = InstanceSet.from_instances(
        [generate_instance(16, 8, 0.3, np.random.default_rng(s)) for s in range(4)], "test")
    scenarios = [(Scenario("16x16", 8, 64), instances)]
    one = evaluate([parse_policy("heuristic")], scenarios, workers=1, batch_size=4)
    two = evaluate([parse_policy("heuristic")], scenarios, workers=2, batch_size=1)
    assert one[0].episodes == two[0].episodes


def test_bad_checkpoint_is_reported(capsys):
    assert mapf_fleet(["evaluate", "--checkpoint", "/no/such.pt", "--quiet"]) == 2
    assert "/no/such.pt" in capsys.readouterr().err


def test_render_writes_a_gif(tmp_path):
    import imageio.v2 as imageio

    out = tmp_path / "ep.gif"
    assert mapf_fleet(["render", "--checkpoint", "heuristic", "--size", "10", "--agents", "3", "--seed", "1",
                       "--max-steps", "12", "--out", str(out)]) == 0
    frames = imageio.mimread(out)
    assert 2 <= len(frames) <= 13
    assert len({f.tobytes() for f in frames}) > 1  # the agents move


def test_structured_families_one_table_per_kind(tmp_path, capsys):
    """--kinds: generated maze / rooms / warehouse maps (seeded, validated), one table per kind
    and side, the protocol's step limit of that side; the same seed gives the same instances."""
    path = tmp_path / "families.json"
    args = ["evaluate", "--checkpoint", "heuristic", "--no-references", "--conflict-rule", "pibt",
            "--kinds", "maze", "rooms", "warehouse", "--sizes", "24", "--agents", "6",
            "--instances", "2", "--quiet", "--json", str(path)]
    assert mapf_fleet(args) == 0
    printed = capsys.readouterr().out
    for kind in ("maze", "rooms", "warehouse"):
        assert f"### {kind} 24x24" in printed
    rows = json.loads(path.read_text())["results"]
    assert [r["map"] for r in rows] == ["maze 24x24", "rooms 24x24", "warehouse 24x24"]
    assert all(r["max_steps"] == 256 and len(r["episodes"]) == 2 for r in rows)
    assert all(r["collisions"] == 0 for r in rows)  # plain PIBT under the shield
    again = tmp_path / "again.json"
    assert mapf_fleet(args[:-1] + [str(again)]) == 0
    assert _figures(path) == _figures(again)
    from mapf_fleet.evaluation.protocol import family_instances

    maze = family_instances("maze", 24, 6, 2, seed=0)
    assert maze.maps.shape == (2, 24, 24) and not (maze.maps[0] == maze.maps[1]).all()


def test_structured_families_refuse_what_does_not_fit(capsys):
    args = ["evaluate", "--checkpoint", "heuristic", "--no-references", "--kinds", "maze",
            "--sizes", "10", "--agents", "60", "--instances", "1", "--quiet"]
    assert mapf_fleet(args) == 2
    err = capsys.readouterr().err
    assert "maze" in err and "60 agents" in err
    assert mapf_fleet(["evaluate", "--checkpoint", "heuristic", "--kinds", "maze", "--map", "x.map",
                       "--agents", "4"]) == 2
    assert "--kinds and --map" in capsys.readouterr().err


def test_evaluate_measures_what_up_runs_by_default():
    """One default everywhere (issue 41 items 3 and 7): with no --conflict-rule, --ranking or
    --guidance, `evaluate` (one-shot and lifelong) runs the rule and the guidance `up` runs, and
    a checkpoint ranks as the fleet's policy nodes rank it (the same `default_ranking` of the
    same recorded metadata). The shipped default records no guidance: it runs under the
    fleet's, the hand-made highways (docs/results.md, "Which guidance is the fleet's default")."""
    from mapf_fleet.coordination.ranking import default_ranking
    from mapf_fleet.coordination.rules import FLEET_GUIDANCE
    from mapf_fleet.evaluation.cli import build_parser
    from mapf_fleet.evaluation.lifelong import build_parser as lifelong_parser
    from mapf_fleet.evaluation.policies import parse_policy, with_conflict_rule, with_guidance
    from mapf_fleet.fleet import parameters
    from mapf_fleet.models.checkpoint import read_checkpoint

    args = build_parser().parse_args([])
    fleet_rule = parameters.SIMULATOR["conflict_rule"].default
    assert args.conflict_rule == [fleet_rule]
    life = lifelong_parser().parse_args(["--lifelong"])
    assert life.conflict_rule == [fleet_rule] and life.guidance is None
    fleet_guidance = parameters.SIMULATOR["guidance"].default
    assert fleet_guidance == parameters.POLICY["guidance"].default == FLEET_GUIDANCE == "highways"
    spec = with_conflict_rule(parse_policy("models/default.pt"), fleet_rule)
    recorded = read_checkpoint("models/default.pt")[1]
    assert spec.resolved_ranking == default_ranking(fleet_rule, recorded.get("rankings"))
    assert "guidance" not in recorded and spec.default_guidance == fleet_guidance
    heuristic = with_conflict_rule(parse_policy("heuristic"), fleet_rule)
    assert [s.guidance for s in with_guidance([spec, heuristic], args.guidance)] == \
        [fleet_guidance, fleet_guidance]
