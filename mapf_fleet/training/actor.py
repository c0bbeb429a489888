"""Ape-X actor: plays episodes with an epsilon-greedy copy of the network and returns them
as replay sequences.

`EpisodeWorker` is a plain class (tests and `use_ray: false` run it in-process); the trainer's
worker pool (`ray_pool.py`) runs one per Ray actor. Rewards are the grid environment's
individual rewards combined by Eq. 2 (`CooperativeReward(alpha)`, neighbours in the 9x9 FOV at
the positions after the step) with the alpha of the current task.

Where the episode's instance comes from: without a training mix, a random map of the task's
setting (`Task.num_agents` agents on `Task.map_size`, density from `obstacle_density`). With a
mix (`TrainConfig.task_mix` non-empty) every episode draws its own map kind, size and agent
count with `mapf_fleet.grid.maps.sample_task_instance(mix, rng)` from the worker's seeded rng,
whatever the stage; the task then only carries alpha and its version (its setting is not used).
The step limit is `episode_step_limit` of the drawn map's side. Environments of one actor may
then hold different agent counts: the batched forward runs once per agent count, and the episode
stats carry the drawn `map_kind`, `map_size` and `num_agents`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from .config import TrainConfig
from .episodes import EpisodeRecord, episode_to_sequences
from .modelio import build_model, hidden_dim, model_step
from .replay import pack_obs


@dataclass(frozen=True)
class Task:
    """What actors should play: the curriculum setting and alpha, tagged with a version so the
    trainer can drop episodes played under an older task."""

    num_agents: int
    map_size: int
    alpha: float
    version: int = 0


class _Recorder:
    """Buffers of one running episode."""

    def __init__(self, obs_bits, positions, hidden):
        self.obs, self.positions, self.hidden = [obs_bits], [positions], [hidden]
        self.actions, self.rewards, self.individual = [], [], []
        self.executed: list = []  # only when the trained action is not the executed one

    def add(self, action, reward, individual, obs_bits, positions, hidden, executed=None):
        self.actions.append(action)
        if executed is not None:
            self.executed.append(executed)
        self.rewards.append(reward)
        self.individual.append(individual)
        self.obs.append(obs_bits)
        self.positions.append(positions)
        self.hidden.append(hidden)

    def finish(self, terminal: bool) -> EpisodeRecord:
        return EpisodeRecord(obs=np.stack(self.obs), positions=np.stack(self.positions),
                             actions=np.stack(self.actions), rewards=np.stack(self.rewards),
                             hidden=np.stack(self.hidden), terminal=terminal,
                             individual_rewards=np.stack(self.individual),
                             executed_actions=(np.stack(self.executed) if self.executed
                                               else None))


class EpisodeWorker:
    def __init__(self, cfg: TrainConfig, actor_index: int, seed: int | None = None):
        torch.set_num_threads(1)
        self.cfg = cfg
        self.index = actor_index
        # one epsilon per environment slot (cfg.epsilon_per_env) or one for the whole actor
        self.epsilons = np.array([cfg.slot_epsilon(actor_index, k)
                                  for k in range(cfg.envs_per_actor)])
        self.gate_slots = np.array([cfg.is_gate_slot(actor_index, k)
                                    for k in range(cfg.envs_per_actor)])
        self.epsilon = float(self.epsilons.max())  # the actor's most exploring slot (logs)
        self.rng = np.random.default_rng(cfg.seed * 1000 + actor_index if seed is None else seed)
        self.model = build_model(cfg).eval()
        self.hidden_dim = hidden_dim(self.model)
        self.weights_version = -1
        self.task: Task | None = None
        self.envs: list = []
        self.keep_records = False  # tests: keep finished EpisodeRecords in `records`
        self.records: list[EpisodeRecord] = []
        self.mix = None  # the training mix (grid.maps.TaskMix) when cfg.task_mix is set
        if cfg.task_mix:
            from mapf_fleet.grid.maps import TaskMix

            self.mix = TaskMix.from_dict(cfg.task_mix)

    # -- control ------------------------------------------------------------------------
    def set_weights(self, state_dict: dict, version: int) -> None:
        self.model.load_state_dict(state_dict)
        self.weights_version = version

    def set_task(self, task: Task) -> None:
        if task != self.task:
            self.task = task
            self.envs = []  # episodes in progress belong to the old task: drop them

    # -- episodes -------------------------------------------------------------------------
    def _new_episode(self, slot: int):
        from mapf_fleet.grid.env import EnvConfig, MAPFEnv
        from mapf_fleet.grid.instance import generate_instance, sample_training_density

        task = self.task
        if self.mix is not None:
            from mapf_fleet.grid.maps import sample_task_instance

            drawn = sample_task_instance(self.mix, self.rng)
            instance, kind, size = drawn.instance, drawn.kind, drawn.size
        else:
            density = (sample_training_density(self.rng)
                       if self.cfg.obstacle_density == "triangular"
                       else float(self.cfg.obstacle_density))
            instance = generate_instance(task.map_size, task.num_agents, density, self.rng)
            kind, size = "random", task.map_size
        env_cfg = EnvConfig(max_steps=self.cfg.episode_step_limit(size),
                            finish_reward=self.cfg.finish_reward, guidance=self.cfg.guidance)
        if slot < len(self.envs) and self.envs[slot] is not None \
                and self.envs[slot]["env"].config == env_cfg:
            env = self.envs[slot]["env"]
            obs = env.reset(instance)
        else:
            env = MAPFEnv(instance, env_cfg)
            obs = env.observe()
        hidden = np.zeros((instance.num_agents, self.hidden_dim), np.float32)
        from mapf_fleet.coordination.factory import make_shield

        shield = make_shield(self.cfg.conflict_rule, instance.grid, instance.goals,
                             guidance=env.guidance)
        state = {"env": env, "obs": obs, "hidden": hidden, "shield": shield,
                 "map_kind": kind, "map_size": int(size),
                 "rec": _Recorder(pack_obs(obs), env.positions.astype(np.int16),
                                  hidden.astype(np.float16))}
        if slot < len(self.envs):
            self.envs[slot] = state
        else:
            self.envs.append(state)

    def _forward(self, envs) -> tuple[np.ndarray, list, list]:
        """Greedy actions (B, N_max) (entries past an environment's agent count are 0) and each
        environment's Q-values (N, 5) and next hidden state (N, H). One batched network step per
        agent count: all environments at once unless a training mix gave them different counts."""
        groups: dict[int, list[int]] = {}
        for slot, e in enumerate(envs):
            groups.setdefault(e["env"].num_agents, []).append(slot)
        greedy = np.zeros((len(envs), max(groups)), np.int64)
        q, hidden = [None] * len(envs), [None] * len(envs)
        for count, slots in groups.items():
            part = [envs[s] for s in slots]
            obs = torch.from_numpy(np.stack([e["obs"] for e in part]))
            pos = torch.from_numpy(np.stack([e["env"].positions for e in part]).astype(np.int64))
            hid = torch.from_numpy(np.stack([e["hidden"] for e in part]))
            last = torch.from_numpy(
                np.stack([e["env"].last_actions for e in part]).astype(np.int64))
            with torch.no_grad():
                out = model_step(self.model, self.cfg.algo, obs, pos, hid, last)
            actions, out_q = out.q.argmax(-1).numpy(), out.q.numpy()
            out_hidden = out.hidden.numpy()
            for i, slot in enumerate(slots):
                greedy[slot, :count] = actions[i]
                q[slot], hidden[slot] = out_q[i], out_hidden[i]
        return greedy, q, hidden

    def _shield(self, envs, chosen: np.ndarray, q: list) -> np.ndarray:
        """The executed actions (B, N_max) under PIBT: each agent's ranking by its Q-values
        (`ranking`), its chosen action (greedy, or the exploring agent's random one)
        moved to the front, arbitrated per environment."""
        from mapf_fleet.coordination.ranking import rank_actions, tie_breakers

        executed = chosen.copy()
        for slot, e in enumerate(envs):
            env = e["env"]
            n = env.num_agents
            ties = tie_breakers(np.arange(n), env.steps)
            ranking = rank_actions(e["obs"], q[slot], self.cfg.ranking, ties=ties)
            first = ranking == chosen[slot, :n][:, None]
            # stable: the chosen action first, the others keep their order
            order = np.argsort(~first, axis=1, kind="stable")
            ranking = np.take_along_axis(ranking, order, axis=1)
            executed[slot, :n] = e["shield"].step(env.positions, ranking).actions
        return executed

    def play(self, task: Task, num_steps: int) -> dict:
        """`set_task(task)`, then `run(num_steps)`: one call of the worker pool."""
        self.set_task(task)
        return self.run(num_steps)

    def run(self, num_steps: int) -> dict:
        """Step every environment `num_steps` times; return the sequences and statistics of
        the episodes that finished. Episodes still running carry over to the next call (same
        task), so short calls lose nothing and keep weights and curriculum fresh."""
        from mapf_fleet.grid.reward import CooperativeReward

        if self.task is None:
            raise RuntimeError("EpisodeWorker.run: set_task() first")
        cfg, task = self.cfg, self.task
        coop = CooperativeReward(task.alpha, radius=4)
        while len(self.envs) < cfg.envs_per_actor:
            self._new_episode(len(self.envs))
        sequences, stats = [], []
        agent_steps, t0 = 0, time.perf_counter()
        # behind the shield, training first choices: the executed actions are recorded beside
        record_executed = cfg.conflict_rule != "revert" and cfg.replay_action == "preferred"
        for _ in range(num_steps):
            envs = self.envs
            actions, q, new_hidden = self._forward(envs)
            # drawn over (B, N_max) whatever the agent counts, so the rng stream is the same
            explore = self.rng.random(actions.shape) < self.epsilons[:len(envs), None]
            if not cfg.explore_all_agents:
                explore[:, 1:] = False
            actions = np.where(explore, self.rng.integers(0, 5, actions.shape), actions)
            # trained: the action the replay stores; actions: what the environment executes
            trained = actions
            if cfg.conflict_rule != "revert":
                actions = self._shield(envs, actions, q)
            if not record_executed:
                trained = actions
            for slot, e in enumerate(envs):
                env = e["env"]
                n = env.num_agents
                obs_next, rewards, done, info = env.step(actions[slot, :n])
                shaped = coop(rewards, env.positions)
                e["obs"], e["hidden"] = obs_next, new_hidden[slot]
                executed = actions[slot, :n].astype(np.uint8) if record_executed else None
                e["rec"].add(trained[slot, :n].astype(np.uint8), shaped, rewards,
                             pack_obs(obs_next), env.positions.astype(np.int16),
                             new_hidden[slot].astype(np.float16), executed=executed)
                agent_steps += n
                if done:
                    record = e["rec"].finish(terminal=bool(info["success"]))
                    if self.keep_records:
                        self.records.append(record)
                    sequences.extend(episode_to_sequences(record, cfg.seq_len, cfg.burn_in,
                                                          cfg.n_step, cfg.gamma))
                    stats.append({"success": bool(info["success"]), "steps": int(info["steps"]),
                                  "num_agents": n, "map_size": e["map_size"],
                                  "map_kind": e["map_kind"],
                                  "alpha": task.alpha, "task_version": task.version,
                                  "actor": self.index, "epsilon": float(self.epsilons[slot]),
                                  "gate": bool(self.gate_slots[slot])})
                    self._new_episode(slot)
        return {"sequences": sequences, "episodes": stats, "agent_steps": agent_steps,
                "seconds": time.perf_counter() - t0, "actor": self.index,
                "weights_version": self.weights_version, "task_version": task.version,
                # this process's CPU time so far (every thread): the trainer sums actor processes
                "pid": os.getpid(), "process_cpu_seconds": time.process_time()}
