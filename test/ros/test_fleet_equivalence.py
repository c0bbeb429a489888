"""The fleet's main test: separate ROS processes reproduce the batched in-process rollout, under
the paper's rule (`--conflict-rule revert`: `run_decentralized(conflict_rule="revert")`) and under the
shield (`--conflict-rule pibt`: `run_decentralized(conflict_rule="pibt")`)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from mapf_fleet.grid.env import MAPFEnv
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.models.checkpoint import load_checkpoint
from mapf_fleet.models.policy import LearnedPolicy


def batched_rollout(checkpoint: str, instance, max_steps: int, comm=None):
    """Actions and positions of the batched evaluator path (MAPFEnv + network.step); when
    `comm` is a list, each step's communication (per robot the sorted partners / requested
    peers) is appended to it."""
    torch.set_num_threads(1)
    model, _ = load_checkpoint(checkpoint)
    policy = LearnedPolicy(model.eval(), device="cpu")  # the evaluator's batched policy
    env = MAPFEnv(instance)
    obs = env.reset()
    policy.reset(1, env.num_agents)
    actions, positions = [], [env.positions.tolist()]
    for _ in range(max_steps):
        act = np.asarray(policy.act(obs[None], env.positions[None]))[0]
        if comm is not None:
            comm.append([np.flatnonzero(row).tolist() for row in policy.comm_mask[0]])
        obs, _, done, _ = env.step(act)
        actions.append(act.tolist())
        positions.append(env.positions.tolist())
        if done:
            break
    return actions, positions


def batched_shielded_rollout(checkpoint: str, instance, max_steps: int, comm=None, anchor=False,
                             rule=None):
    """The batched evaluator's shielded path (`evaluation.runner.run_decentralized(...,
    shield="pibt")` with `CheckpointBatchPolicy`): each step the policy's Q-values ranked by
    `rank_actions` (the rule's default mode, `default_ranking`: the fleet's policy nodes follow
    the conflict rule too; ties `tie_breakers(agent ids, step)`), one `PIBTShield` for
    the episode, the executed actions fed back as DCC's last action. Returns (first choices,
    executed actions, positions, overridden robot ids per step). `rule` (a shield rule) wins
    over `anchor`."""
    from mapf_fleet.coordination.factory import make_shield
    from mapf_fleet.coordination.ranking import default_ranking, rank_actions, tie_breakers

    torch.set_num_threads(1)
    model, _ = load_checkpoint(checkpoint)
    policy = LearnedPolicy(model.eval(), device="cpu")
    env = MAPFEnv(instance)
    obs = env.reset().astype(np.float32)[None]
    n = env.num_agents
    policy.reset(1, n)
    rule = rule or ("pibt_anchor" if anchor else "pibt")
    shield = make_shield(rule, instance.grid, instance.goals)
    mode = default_ranking(rule)
    choices, executed, overridden = [], [], []
    positions = [env.positions.tolist()]
    for tick in range(max_steps):
        policy.act(obs, env.positions[None])
        if comm is not None:
            comm.append([np.flatnonzero(row).tolist() for row in policy.comm_mask[0]])
        prefs = rank_actions(obs, policy.q_values, mode,
                             ties=tie_breakers(np.arange(n), tick)[None])[0]
        step = shield.step(env.positions, prefs)
        policy.set_last_actions(step.actions[None])
        step_obs, _, done, info = env.step(step.actions)
        assert not np.asarray(info["collisions"]).any()
        obs = step_obs.astype(np.float32)[None]
        choices.append(prefs[:, 0].tolist())
        executed.append(step.actions.tolist())
        overridden.append(np.flatnonzero(step.overridden).tolist())
        positions.append(env.positions.tolist())
        if done:
            break
    return choices, executed, positions, overridden


def run_fleet(tmp_path, env, checkpoint, seed, num_robots, size, max_steps, extra=()):
    record = tmp_path / f"run_{seed}.json"
    cmd = [sys.executable, "-m", "mapf_fleet.cli", "up", "--checkpoint", checkpoint,
           "--num-robots", str(num_robots), "--size", str(size), "--seed", str(seed),
           "--max-steps", str(max_steps), "--record", str(record), "--quiet",
           "--guidance", "none", *extra]  # the batched rollouts here are unguided (MAPFEnv)
    # ros_env (test/conftest.py) sets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and ROS_DOMAIN_ID
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True,
                          timeout=240)
    assert record.exists(), proc.stdout + proc.stderr
    return json.loads(record.read_text()), proc


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("algo", ["dhc", "dcc_sensitive"])
def test_separate_processes_match_batched_rollout(tmp_path, ros_env, checkpoints, algo):
    """DCC runs a checkpoint whose causal sets are not empty (make_sensitive), so requests and
    replies really travel over the services; the recorded communication must equal the batched
    step's comm_mask, and the actions and trajectory must be the same."""
    # one robot per process, then 4 robots' nodes per process (the large-fleet layout)
    for seed, per_process in ((3, 1), (11, 4)):
        instance = generate_instance(10, 8, 0.2, seed)
        expected_comm = []
        expected_actions, expected_positions = batched_rollout(checkpoints[algo], instance, 16,
                                                               expected_comm)
        record, proc = run_fleet(tmp_path, ros_env, checkpoints[algo], seed, 8, 10, 16,
                                 extra=["--density", "0.2", "--nodes-per-process", str(per_process),
                                        "--conflict-rule", "revert"])
        assert record["missed_decisions"] == 0, proc.stdout
        assert record["actions"] == expected_actions, f"seed {seed}"
        assert record["positions"] == expected_positions, f"seed {seed}"
        assert [[sorted(r) for r in tick] for tick in record["requested"]] == expected_comm
        # the test can fail: a random policy on 8 robots does move (not all stay)
        assert np.any(np.asarray(record["actions"]) != 0)
        # messages really went between robots: DCC requests + replies (2 per request), DHC
        # partner vectors (one per partner and round)
        requests = sum(len(r) for tick in record["requested"] for r in tick)
        assert requests > 0, "nobody communicated: the test would prove nothing"
        # DCC: a request and its reply; DHC: the partner's vector in each of the 2 rounds
        assert sum(map(sum, record["messages"])) == 2 * requests


@pytest.mark.ros
@pytest.mark.slow
def test_single_process_matches_batched_rollout(tmp_path, ros_env, checkpoints):
    """Every robot in one process (one hub, local delivery, batched inference): same actions."""
    for algo in ("dhc", "dcc_sensitive"):
        instance = generate_instance(10, 8, 0.2, 5)
        expected_actions, expected_positions = batched_rollout(checkpoints[algo], instance, 16)
        record, proc = run_fleet(tmp_path, ros_env, checkpoints[algo], 5, 8, 10, 16,
                                 extra=["--density", "0.2", "--single-process",
                                        "--conflict-rule", "revert"])
        assert record["missed_decisions"] == 0, proc.stdout
        assert record["actions"] == expected_actions, algo
        assert record["positions"] == expected_positions, algo


def assert_fleet_matches_rollout(record, proc, rule, where, choices, executed, positions,
                                 overridden):
    """The fleet's record under `rule` equals a `batched_shielded_rollout`: trajectory, executed
    and first-choice actions, overridden robots; no decision missed, nothing reverted."""
    assert record["conflict_rule"] == rule and record["missed_decisions"] == 0, proc.stdout
    assert record["positions"] == positions, where
    assert record["executed"] == executed, where
    assert record["actions"] == choices, where
    assert record["overridden"] == overridden, where
    assert record["collisions"] == 0 and not any(record["collided"]), where


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("algo", ["dhc", "dcc_sensitive"])
def test_shielded_fleet_matches_batched_shielded_rollout(tmp_path, ros_env, checkpoints, algo):
    """`--conflict-rule pibt`: the robots publish their ranked actions, the simulator runs the
    shield; the trajectory, the executed and first-choice actions, the overridden robots and
    (DCC) the communication equal the evaluator's shielded path, on dense instances of 12
    robots: one robot per process, then 4 per process, then 3 processes of 4-5 robots."""
    overridden = 0
    for seed, per_process in ((2, 1), (7, 4), (13, 5)):
        instance = generate_instance(9, 12, 0.2, seed)
        expected_comm = []
        choices, executed, positions, expected_overridden = batched_shielded_rollout(
            checkpoints[algo], instance, 20, expected_comm)
        record, proc = run_fleet(tmp_path, ros_env, checkpoints[algo], seed, 12, 9, 20,
                                 extra=["--density", "0.2", "--nodes-per-process",
                                        str(per_process), "--conflict-rule", "pibt"])
        where = f"{algo} seed {seed}: {record.get('summary')}"
        assert_fleet_matches_rollout(record, proc, "pibt", where, choices, executed, positions,
                                     expected_overridden)
        assert [[sorted(r) for r in tick] for tick in record["requested"]] == expected_comm
        assert np.any(np.asarray(executed) != 0)
        overridden += sum(map(len, expected_overridden))
    # the shield really changed moves, so the test compares PIBT's decisions, not just argmax
    assert overridden > 0


@pytest.mark.ros
@pytest.mark.slow
def test_anchored_fleet_matches_batched_anchored_rollout(tmp_path, ros_env, checkpoints):
    """`--conflict-rule pibt_anchor`: the simulator's arbiter anchors the top-priority robot
    exactly as the evaluator's `--conflict-rule pibt_anchor` (one dense instance, 4 robots per process)."""
    instance = generate_instance(9, 12, 0.2, 7)
    choices, executed, positions, expected_overridden = batched_shielded_rollout(
        checkpoints["dcc_sensitive"], instance, 20, anchor=True)
    plain = batched_shielded_rollout(checkpoints["dcc_sensitive"], instance, 20)
    assert plain[1] != executed  # the anchor changed moves: the comparison is not vacuous
    record, proc = run_fleet(tmp_path, ros_env, checkpoints["dcc_sensitive"], 7, 12, 9, 20,
                             extra=["--density", "0.2", "--nodes-per-process", "4",
                                    "--conflict-rule", "pibt_anchor"])
    assert_fleet_matches_rollout(record, proc, "pibt_anchor", f"seed 7: {record.get('summary')}",
                                 choices, executed, positions, expected_overridden)


@pytest.mark.ros
@pytest.mark.slow
def test_swap_hindrance_fleet_matches_batched_rollout(tmp_path, ros_env, checkpoints):
    """`--conflict-rule pibt_anchor_swap_hindrance`: the simulator's arbiter runs the PIBT
    variants exactly as the evaluator's `--conflict-rule pibt_anchor_swap_hindrance` (one dense
    instance, 4 robots per process)."""
    rule = "pibt_anchor_swap_hindrance"
    instance = generate_instance(9, 12, 0.2, 7)
    choices, executed, positions, expected_overridden = batched_shielded_rollout(
        checkpoints["dcc_sensitive"], instance, 20, rule=rule)
    anchored = batched_shielded_rollout(checkpoints["dcc_sensitive"], instance, 20, anchor=True)
    assert anchored[1] != executed  # the variants changed moves: the comparison is not vacuous
    record, proc = run_fleet(tmp_path, ros_env, checkpoints["dcc_sensitive"], 7, 12, 9, 20,
                             extra=["--density", "0.2", "--nodes-per-process", "4",
                                    "--conflict-rule", rule])
    assert_fleet_matches_rollout(record, proc, rule, f"seed 7: {record.get('summary')}",
                                 choices, executed, positions, expected_overridden)
