"""Training throughput on this machine, one core: actor agent-steps/s and learner samples/s.

For each preset (paper-size and CPU configs, DHC and DCC) at the final curriculum setting
(12 / 16 agents on 40x40): an actor plays with the preset's network (its agent-steps/s is
measured), its sequences fill a replay, then the learner runs a few updates.

Learner figures:
  sequences/s     replayed sequences (seq_len steps of every agent) per second
  transitions/s   agent-transitions with a loss per second (every agent, every trained step)
The reference learner trains one agent-0 transition per sample and needs about 390 s per
batch of 192 on one core (DESIGN.md section 4): 0.49 transitions/s. "speed-up" below is
transitions/s divided by that. The batch is smaller than the paper's (per-sample cost is linear
in the batch), so a paper-size update takes batch_size / sequences-per-second seconds.

    .venv/bin/python benchmarks/bench_training.py [--updates 2] [--batch 4] [--only dhc_paper]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from mapf_fleet.training.actor import EpisodeWorker, Task
from mapf_fleet.training.config import load_config
from mapf_fleet.training.learner import Learner
from mapf_fleet.training.modelio import hidden_dim
from mapf_fleet.training.replay import PrioritizedSequenceReplay

CONFIGS = Path(__file__).resolve().parent.parent / "config" / "training"
REFERENCE_TRANSITIONS_PER_S = 192 / 390.0


def bench(name: str, batch: int, updates: int, actor_steps: int) -> None:
    cfg = load_config(CONFIGS / f"{name}.yaml").replace(device="cpu", envs_per_actor=2)
    worker = EpisodeWorker(cfg, actor_index=cfg.num_actors - 1)
    worker.set_task(Task(cfg.final_agents, cfg.final_map_size, 0.0))
    worker.run(2)  # warm-up (instance generation, first allocations)
    t0 = time.perf_counter()
    sequences, agent_steps = [], 0
    # Short episodes so some finish and produce sequences within the measured time.
    worker.cfg = worker.cfg.replace(max_episode_steps=max(cfg.seq_len + cfg.n_step, 24))
    worker.envs = []
    while time.perf_counter() - t0 < 1e9:
        result = worker.run(actor_steps)
        sequences += result["sequences"]
        agent_steps += result["agent_steps"]
        if len(sequences) >= batch:
            break
    actor_rate = agent_steps / (time.perf_counter() - t0)
    learner = Learner(cfg, device="cpu")
    replay = PrioritizedSequenceReplay(max(len(sequences), batch), cfg.window_len, cfg.seq_len,
                                       cfg.final_agents, hidden_dim(learner.model))
    for seq in sequences:
        replay.add(seq)
    sample = replay.sample(batch, cfg.priority_beta)
    learner.update(sample)  # warm-up
    t0 = time.perf_counter()
    transitions = 0
    for _ in range(updates):
        sample = replay.sample(batch, cfg.priority_beta)
        priorities, stats = learner.update(sample)
        replay.update_priorities(sample.indices, priorities)
        transitions += stats["transitions"]
    seconds = time.perf_counter() - t0
    seq_rate = updates * batch / seconds
    tr_rate = transitions / seconds
    print(f"{name:<11} {cfg.algo} model={cfg.model_preset:<5} {cfg.final_agents} agents "
          f"{cfg.final_map_size}x{cfg.final_map_size} | actor {actor_rate:8.0f} agent-steps/s | "
          f"learner batch {batch}: {seq_rate:7.2f} sequences/s, {tr_rate:9.1f} transitions/s, "
          f"speed-up vs reference {tr_rate / REFERENCE_TRANSITIONS_PER_S:7.1f}x, "
          f"paper batch {cfg.batch_size} -> {cfg.batch_size / seq_rate:7.1f} s/update",
          flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=2)
    parser.add_argument("--batch", type=int, default=4, help="sequences per update (paper size)")
    parser.add_argument("--cpu-batch", type=int, default=32, help="sequences per update (CPU)")
    parser.add_argument("--actor-steps", type=int, default=16)
    parser.add_argument("--only", nargs="*", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    names = ["dhc_paper", "dcc_paper", "dhc_cpu", "dcc_cpu"]
    for name in args.only or names:
        batch = args.batch if name.endswith("paper") else args.cpu_batch
        bench(name, batch, args.updates, args.actor_steps)


if __name__ == "__main__":
    main()
