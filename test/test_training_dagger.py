"""DAgger behind the arbiter (mapf_fleet.training.dagger): labels, shards, resume, learner.

Tiny maps, a few agents, the `small` DCC network: seconds in all; Ray only in the slow test of the
shared worker pool's Ray path."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mapf_fleet.coordination.planners import ClassicalPlanner, positions_to_actions
from mapf_fleet.grid.heuristic import bfs_distances_many
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.grid.maps import DENSE, capacity, generate_kind_instance
from mapf_fleet.models.checkpoint import build_model, load_checkpoint, save_checkpoint
from mapf_fleet.models.config import ModelConfig
from mapf_fleet.training import dagger
from mapf_fleet.training.modelio import model_step
from mapf_fleet.training.replay import unpack_obs


@pytest.fixture
def small_checkpoint(tmp_path):
    torch.manual_seed(0)
    model = build_model(ModelConfig.preset("dcc", "small"))
    path = tmp_path / "small.pt"
    save_checkpoint(path, model, {"alpha": 0.0, "curriculum": {}, "learner_steps": 0,
                                  "training_config": {}})
    return str(path)


def tiny_config(init: str, **changes) -> dagger.DaggerConfig:
    values = dict(init_checkpoint=init, rounds=1, episodes_per_round=2, use_ray=False,
                  tasks=[{"kind": "random", "size": 9, "agents": [3, 4], "weight": 1.0,
                          "max_steps": 24}],
                  late_tasks=[], heldout=[{"kind": "random", "size": 9, "agents": 3,
                                           "max_steps": 24}],
                  heldout_count=2, updates_per_round=3, batch_windows=2, seq_len=6, burn_in=3,
                  device="cpu")
    values.update(changes)
    return dagger.DaggerConfig(**values)


def test_labels_are_lacam_first_moves():
    inst = generate_instance(10, 5, 0.1, 3)
    labeller = dagger.LaCAMLabeller(2.0, 3.0, 32)
    dist = bfs_distances_many(inst.grid, inst.goals)
    state = dagger.LabelState(inst.grid, inst.starts, inst.goals, dist, 0, 64)
    labels, status = labeller.label(state)
    plan = ClassicalPlanner("lacam", 2.0, 0).plan(inst.grid, inst.starts, inst.goals)
    assert status == "ok" and plan.complete
    assert labels.tolist() == positions_to_actions(plan.positions[:2])[0].tolist()
    # a plan longer than the filter allows gives no labels, and says why
    strict = dagger.LaCAMLabeller(2.0, 0.5, 0)
    labels, status = strict.label(state)
    assert status == "too_long" and (labels == -1).all()
    assert labeller.plan_limit(10, 256) == 62 and labeller.plan_limit(100, 128) == 128


def test_dense_kind_pads_a_small_map_with_obstacles():
    sides = set()
    for seed in range(12):
        inst = generate_kind_instance(DENSE, 21, 48, seed)
        assert inst.size == (21, 21)
        free_rows = np.flatnonzero((inst.grid == 0).any(1))
        side = int(free_rows.max()) + 1
        assert 17 <= side <= 21 and (inst.grid[side:] == 1).all() and (inst.grid[:, side:] == 1).all()
        sides.add(side)
    assert len(sides) > 1
    assert capacity(DENSE, 21) == int(0.25 * 17 * 17)


def test_episode_windows_replay_the_policy(small_checkpoint):
    """The stored windows (hidden state at the window start, inputs along the rollout) give the
    Q-values of an unroll of the whole episode from its start."""
    model, _ = load_checkpoint(small_checkpoint)
    inst = generate_instance(9, 4, 0.1, 1)
    out = dagger.play_episode(model, inst, 20, "pibt_anchor", "q_then_distance",
                              torch.device("cpu"), dagger.LaCAMLabeller(1.0, 3.0, 32), 0.5, 1,
                              np.random.default_rng(0), seq_len=6, burn_in=3)
    a = out["arrays"]
    length = len(a["labels"])
    assert length == out["steps"] and out["labels"] == int((a["labels"] >= 0).sum())
    assert a["hidden_starts"].tolist() == dagger.window_starts(length, 6, 3).tolist()
    obs = torch.as_tensor(unpack_obs(a["obs_bits"]))
    pos = torch.as_tensor(a["positions"].astype(np.int64))
    last = torch.as_tensor(a["last_actions"].astype(np.int64))
    assert (last[0] == -1).all()
    h = torch.zeros(1, 4, model.config.hidden_dim)
    full = []
    with torch.no_grad():
        for t in range(length):
            o = model_step(model, "dcc", obs[t][None], pos[t][None], h, last[t][None])
            h = o.hidden
            full.append(o.q[0])
        data = dagger.LabelledData(6, 3)
        data.add("x", a)
        for e, j in data.windows:
            win = data.window(e, j)
            h = torch.as_tensor(win["hidden"])[None]
            for s in range(len(win["obs"])):
                o = model_step(model, "dcc", torch.as_tensor(win["obs"][s])[None],
                               torch.as_tensor(win["positions"][s])[None], h,
                               torch.as_tensor(win["last"][s])[None])
                h = o.hidden
                t = int(a["hidden_starts"][j]) + s
                assert torch.allclose(o.q[0], full[t], atol=2e-2), (j, s)


def test_run_writes_shards_and_resume_skips_them(small_checkpoint, tmp_path):
    run = tmp_path / "run"
    cfg = tiny_config(small_checkpoint)
    result = dagger.Dagger(cfg, run, log=lambda m: None).run()
    assert result["round"] == 1
    manifest = json.loads((run / "data" / "manifest.json").read_text())
    assert sorted(manifest["shards"]) == ["r000_e000.npz", "r000_e001.npz"]
    counters = json.loads((run / "state.json").read_text())["counters"]
    assert counters["labels"] == sum(m["labels"] for m in manifest["shards"].values()) > 0
    assert (run / "checkpoints" / "round_000.pt").is_file()
    _, meta = load_checkpoint(run / "checkpoints" / "round_000.pt")
    assert meta["extra"]["dagger"]["round"] == 0 and meta["extra"]["dagger"]["labels"] > 0
    # the ranking it was trained behind, its default there in the evaluator and the fleet
    assert meta["rankings"] == {cfg.conflict_rule: cfg.ranking} == {"pibt_anchor": "q_then_distance"}
    curve = json.loads((run / "curve.json").read_text())
    assert [(r["round"], r["policy"]) for r in curve] == [(-1, "plain_pibt"), (-1, "init"),
                                                          (0, "dagger")]
    stamps = {p.name: p.stat().st_mtime_ns for p in (run / "data").glob("r000_*.npz")}
    # killed after the second shard was written but before the manifest recorded it, in round 0
    del manifest["shards"]["r000_e001.npz"]
    (run / "data" / "manifest.json").write_text(json.dumps(manifest))
    state = json.loads((run / "state.json").read_text())
    state.update(round=0, phase="collect")
    (run / "state.json").write_text(json.dumps(state))
    resumed = dagger.Dagger(tiny_config(small_checkpoint, rounds=2), run, log=lambda m: None)
    resumed.run()
    after = {p.name: p.stat().st_mtime_ns for p in (run / "data").glob("r000_*.npz")}
    assert after == stamps  # nothing replayed: the shard was adopted
    manifest = json.loads((run / "data" / "manifest.json").read_text())
    assert sorted(manifest["shards"]) == ["r000_e000.npz", "r000_e001.npz", "r001_e000.npz",
                                          "r001_e001.npz"]
    assert json.loads((run / "state.json").read_text())["round"] == 2


def test_a_cost_to_go_run_warm_starts_and_records_the_channel(small_checkpoint, tmp_path):
    """`observation: cost_to_go` on a paper checkpoint: round 0 plays exactly as the init
    checkpoint, the shards keep the channel beside the bits (int8 `ctg`), the windows rebuild
    the 7-channel observation and the round's checkpoint records the option."""
    run = tmp_path / "run"
    driver = dagger.Dagger(tiny_config(small_checkpoint, observation="cost_to_go"), run,
                           log=lambda m: None)
    assert driver.model.config.observation == "cost_to_go"
    init, _ = load_checkpoint(small_checkpoint)
    inst = generate_instance(9, 4, 0.1, 1)
    plays = [dagger.play_episode(m, inst, 20, "pibt_anchor", "q_then_distance",
                                 torch.device("cpu"), seq_len=6, burn_in=3)
             for m in (init, driver.model)]
    assert "ctg" not in plays[0]["arrays"] and plays[1]["arrays"]["ctg"].dtype == np.int8
    for key in ("obs_bits", "positions", "last_actions", "hidden"):
        np.testing.assert_array_equal(plays[0]["arrays"][key], plays[1]["arrays"][key])
    assert driver.run()["round"] == 1
    shards = sorted((run / "data").glob("r000_*.npz"))
    assert len(shards) == 2
    for shard in shards:
        arrays, _ = dagger.read_shard(shard)
        assert arrays["ctg"].shape == (*arrays["labels"].shape, 9, 9)
    win = driver.data.window(*driver.data.windows[0])
    assert win["obs"].shape[2:] == (7, 9, 9)
    _, meta = load_checkpoint(run / "checkpoints" / "round_000.pt")
    assert meta["model_config"]["observation"] == "cost_to_go"
    assert meta["training_config"]["dagger"]["observation"] == "cost_to_go"
    # a paper network cannot read the run's shards: the resume names the state file
    with pytest.raises(dagger.DaggerConfigError, match="state.pt.*observation"):
        dagger.Dagger(tiny_config(small_checkpoint, observation="paper"), run,
                      log=lambda m: None)


def test_training_fits_the_labels(small_checkpoint, tmp_path):
    cfg = tiny_config(small_checkpoint, lr=3e-3, batch_windows=4)
    learner = dagger.Dagger(cfg, tmp_path / "run", log=lambda m: None)
    model, _ = load_checkpoint(small_checkpoint)
    for k, seed in enumerate(range(3)):
        inst = generate_instance(9, 4, 0.1, seed)
        out = dagger.play_episode(model, inst, 20, "pibt_anchor", "q_then_distance",
                                  torch.device("cpu"), dagger.LaCAMLabeller(1.0, 3.0, 32),
                                  seq_len=6, burn_in=3)
        learner.data.add(f"e{k}", out["arrays"])
        learner.manifest["shards"][f"e{k}"] = {}

    def loss():
        total = count = 0.0
        with torch.no_grad():
            for e, j in learner.data.windows:
                value, c, _ = dagger.window_loss(learner.model, "dcc", learner.data.window(e, j),
                                                 torch.device("cpu"), "cross_entropy", 0.8)
                total, count = total + float(value), count + c
        return total / count

    learner.load_data = lambda: None  # the episodes above are the data set
    before = loss()
    learner.cfg.updates_per_round = 40
    learner._wall, learner._proc = time.monotonic(), time.process_time()
    learner.train(0)
    assert loss() < 0.7 * before


def test_config_errors_name_the_field(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("rounds: 2\nlabel_tim_limit: 1\n")
    with pytest.raises(dagger.DaggerConfigError, match="label_tim_limit"):
        dagger.load_config(bad)
    with pytest.raises(dagger.DaggerConfigError, match="tasks.*kind 'forest'"):
        dagger.config_from_dict({"tasks": [{"kind": "forest", "size": 20, "agents": [4],
                                            "weight": 1, "max_steps": 64}]})
    with pytest.raises(dagger.DaggerConfigError, match="conflict_rule"):
        dagger.config_from_dict({"conflict_rule": "revert"})
    with pytest.raises(dagger.DaggerConfigError, match="'observation' = 'foo'"):
        dagger.config_from_dict({"observation": "foo"})
    for name in ("dagger_dcc.yaml", "dagger_dhc.yaml"):  # the shipped configs load
        cfg = dagger.load_config(Path(__file__).parents[1] / "config" / "training" / name)
        assert cfg.conflict_rule == "pibt_anchor"


def test_cli_registered(tmp_path):
    from mapf_fleet.cli import COMMANDS, main

    assert COMMANDS["dagger"][0] == "mapf_fleet.training.dagger"
    with pytest.raises(SystemExit) as exit_info:
        main(["dagger", "--help"])
    assert exit_info.value.code == 0
    # no run to resume and no config: one error line, exit 2
    assert main(["dagger", "--run-dir", str(tmp_path / "none")]) == 2


def test_labelling_backs_off_after_failed_states(small_checkpoint):
    class Failing:
        calls: list = []

        def label(self, state):
            self.calls.append(state.step)
            return dagger.Labels(np.full(len(state.positions), -1, np.int64), "unsolved")

    model, _ = load_checkpoint(small_checkpoint)
    inst = generate_instance(12, 6, 0.2, 5)
    labeller = Failing()
    out = dagger.play_episode(model, inst, 40, "pibt_anchor", "q", torch.device("cpu"),
                              labeller, label_interval=1, backoff_max=8)
    steps, t, expected, wait = out["steps"], 0, [], 1
    while t < steps:  # calls at 0, 2, 6, 14, 22, 30, ...
        expected.append(t)
        wait = min(wait * 2, 8)
        t += wait
    assert out["label_calls"] == len(expected) == out["unsolved"]
    assert labeller.calls == expected  # the labeller is told the step of each state
    assert out["labels"] == 0 and (out["arrays"]["labels"] == -1).all()


def _fake_run(path: Path, loss: str, rounds: list[float]) -> Path:
    path.mkdir()
    (path / dagger.CONFIG_FILE).write_text(f"loss: {loss}\nobservation: null\n")
    curve = [{"round": -1, "policy": "plain_pibt", "labels": 0, "cpu_seconds": 1.0,
              "d_success": 0.5, "d_steps": 100.0},
             {"round": -1, "policy": "init", "labels": 0, "cpu_seconds": 2.0,
              "d_success": 0.1, "d_steps": 120.0}]
    curve += [{"round": k, "policy": "dagger", "labels": 1000 * (k + 1), "cpu_seconds": 3600.0 * (k + 1),
               "d_success": s, "d_steps": 90.0 - k} for k, s in enumerate(rounds)]
    (path / dagger.CURVE_JSON).write_text(json.dumps(curve))
    return path


def test_compare_runs_prints_the_ab_side_by_side(tmp_path, capsys):
    a = _fake_run(tmp_path / "a", "cross_entropy", [0.2, 0.4, 0.6])
    b = _fake_run(tmp_path / "b", "margin", [0.3, 0.5, 0.9])
    table = dagger.compare_runs([a, b], last=2)
    rows = table.splitlines()
    assert rows[0].startswith("| run | loss |") and "d success (steps)" in rows[0]
    assert "| a | cross_entropy | init | 3 | 3,000 | 3.00 | plain PIBT | 0.50 (100) |" in table
    assert "| round 2 | 0.60 (88) |" in table and "| round 2 | 0.90 (88) |" in table
    # the mean of the last two rounds: (0.4 + 0.6) / 2 and (89 + 88) / 2
    assert "| mean of rounds 1-2 | 0.50 (88) |" in table
    assert "| mean of rounds 1-2 | 0.70 (88) |" in table
    assert dagger.main(["--compare", str(a), str(b), "--last", "2"]) == 0
    assert capsys.readouterr().out.strip() == table
    png = tmp_path / "curves.png"
    assert dagger.main(["--compare", str(a), str(b), "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"curves: {png}" in capsys.readouterr().out
    # not a run directory: one line naming it, exit 2
    assert dagger.main(["--compare", str(tmp_path / "nope")]) == 2
    assert "nope: not a DAgger run directory" in capsys.readouterr().err


@pytest.mark.slow
def test_a_round_on_two_ray_workers(small_checkpoint, tmp_path):
    """The shared worker pool's Ray path: a local Ray with two workers plays and labels every
    episode of the round."""
    cfg = tiny_config(small_checkpoint, use_ray=True, num_cpus=2, num_workers=2,
                      episodes_per_round=4)
    result = dagger.Dagger(cfg, tmp_path / "run", log=lambda m: None).run()
    assert result["round"] == 1
    manifest = json.loads((tmp_path / "run" / "data" / "manifest.json").read_text())
    assert sorted(manifest["shards"]) == [f"r000_e00{i}.npz" for i in range(4)]
    assert result["counters"]["labels"] > 0
    assert {m["job"]["episode"] for m in manifest["shards"].values()} == {0, 1, 2, 3}


def test_wait_labels_are_capped_at_random_and_the_same_every_load():
    """cap_wait_labels keeps at most `cap` of the kept labels as waits, drops only waits, and
    the aggregate applies it per shard with the shard's name as seed (the same labels on
    every load; the shard itself keeps them all)."""
    from mapf_fleet.training.dagger.data import cap_wait_labels

    rng = np.random.default_rng(0)
    labels = rng.choice([-1, 0, 0, 0, 1, 2, 3, 4], size=(40, 16)).astype(np.int8)
    capped = cap_wait_labels(labels, 0.2, seed=7)
    kept = capped >= 0
    assert (capped == 0).sum() <= 0.2 * kept.sum() + 1e-9
    assert (capped[capped != labels] == -1).all() and (labels[capped != labels] == 0).all()
    assert ((labels > 0) == (capped > 0)).all()  # every move label kept
    np.testing.assert_array_equal(capped, cap_wait_labels(labels, 0.2, seed=7))
    assert cap_wait_labels(labels, 1.0, seed=7) is labels
    assert (cap_wait_labels(labels, 0.0, seed=7) != 0).all()
    arrays = {"labels": labels, "hidden_starts": np.arange(0, 40, 6)}
    a, b = dagger.LabelledData(6, 3, wait_cap=0.2), dagger.LabelledData(6, 3, wait_cap=0.2)
    a.add("r000_e001.npz", arrays)
    b.add("r000_e001.npz", arrays)
    np.testing.assert_array_equal(a.episodes[0]["labels"], b.episodes[0]["labels"])
    assert (arrays["labels"] == labels).all()  # the shard's arrays untouched
