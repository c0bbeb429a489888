"""Training throughput on this machine, one torch thread: actor agent-steps/s and the learner's
cost per sampled sequence. Everything printed under "measured" is measured by this run.

For each preset (paper-size and CPU configs, DHC and DCC) at the final curriculum setting
(12 / 16 agents on 40x40): an actor plays episodes of up to `--episode-steps` steps with the
preset's network (its agent-steps/s is measured), its sequences fill a replay, then the learner runs `--updates` updates on batches of
`--batch` sequences (after one warm-up update). Learner figures per sampled sequence:
  wall s/seq     wall-clock seconds per sequence (inflated when other processes share the cores)
  CPU s/seq      process CPU seconds per sequence (all threads), the unit of the reference figures
  unrolled       observation steps each network unrolls per sequence (burn-in + trained + n-step)
  transitions/s  agent-transitions with a loss per wall second (every agent, every trained step;
                 the reference learner trains one agent-0 transition per sequence)
  paper batch    batch_size x wall s/seq: one update at the preset's batch size
DCC presets are timed twice with `--dcc-masks recompute replay`: "recompute" is the learner's
default (the unrolled networks recompute the decision-causal masks); "replay" passes
`comm_masks=` masks chosen by the target network before the timing starts, a stand-in for masks
an actor would record (the actor does not record them today), so it measures what replaying
would cost, not a mode training can use yet. With a fresh learner (online = target weights) both
give the same loss; the line "same loss" checks that on the first batch. DCC learners start from
`models.synthetic.make_sensitive` weights (greedy actions react to single neighbours, so agents
communicate; the default init hardly ever does, which would make both variants look cheaper);
`--fresh-weights` uses the default init.

The reference figures are not measured here: they are constants with their source, printed last.

    .venv/bin/python benchmarks/bench_training.py [--updates 2] [--batch 4] [--only dcc_paper]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from mapf_fleet.models.synthetic import make_sensitive
from mapf_fleet.training.actor import EpisodeWorker, Task
from mapf_fleet.training.config import load_config
from mapf_fleet.training.learner import Learner
from mapf_fleet.training.modelio import hidden_dim
from mapf_fleet.training.replay import PrioritizedSequenceReplay

CONFIGS = Path(__file__).resolve().parent.parent / "config" / "training"

# Reference learners, measured side by side with the reference DHC / DCC code on these machines
# (paper sizes, float32); source: ../shared/DESIGN.md section 4 ("Cost on these machines").
REFERENCE_SOURCE = "../shared/DESIGN.md section 4"
REFERENCE_DHC_CPU_S_PER_SEQUENCE = (0.76, 0.92)  # 12 agents, 16 + 2 steps unrolled
REFERENCE_DCC_CPU_S_PER_SEQUENCE = (0.36, 0.38)  # 16 agents, 23 unrolled steps, masks replayed
REFERENCES = {
    "dhc": (REFERENCE_DHC_CPU_S_PER_SEQUENCE, "12 agents, 16+2 steps unrolled"),
    "dcc": (REFERENCE_DCC_CPU_S_PER_SEQUENCE,
            "16 agents, 23 steps unrolled, causal masks replayed from the actor"),
}


def collect(cfg, batch: int, actor_steps: int, episode_steps: int):
    """Play the final task until `batch` sequences exist; return (sequences, agent-steps/s)."""
    worker = EpisodeWorker(cfg, actor_index=cfg.num_actors - 1)
    worker.set_task(Task(cfg.final_agents, cfg.final_map_size, 0.0))
    worker.run(2)  # warm-up (instance generation, first allocations)
    worker.cfg = worker.cfg.replace(max_episode_steps=episode_steps, max_steps_per_map_side=0.0)
    worker.envs = []
    t0 = time.perf_counter()
    sequences, agent_steps = [], 0
    while len(sequences) < batch:
        result = worker.run(actor_steps)
        sequences += result["sequences"]
        agent_steps += result["agent_steps"]
    return sequences, agent_steps / (time.perf_counter() - t0)


def make_learner(cfg, sensitive: bool, seed: int = 0) -> Learner:
    """A fresh learner; `sensitive`: weights under which DCC communicates (online = target)."""
    torch.manual_seed(seed)
    learner = Learner(cfg, device="cpu")
    if sensitive:
        make_sensitive(learner.model, seed)
        learner.sync_target()
    return learner


def time_learner(cfg, samples, masks, sensitive: bool) -> dict:
    """Warm-up update on samples[0], then one timed update per further sample."""
    learner = make_learner(cfg, sensitive)
    learner.update(samples[0], comm_masks=masks[0])
    wall0, cpu0 = time.perf_counter(), time.process_time()
    transitions, sequences = 0, 0
    for sample, mask in zip(samples[1:], masks[1:]):
        _, stats = learner.update(sample, comm_masks=mask)
        transitions += stats["transitions"]
        sequences += len(sample.indices)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return {"wall": wall / sequences, "cpu": cpu / sequences, "transitions": transitions / wall}


def bench(name: str, batch: int, updates: int, actor_steps: int, dcc_masks: list[str],
          sensitive: bool, episode_steps: int) -> None:
    cfg = load_config(CONFIGS / f"{name}.yaml").replace(device="cpu", envs_per_actor=2)
    episode_steps = episode_steps or cfg.episode_step_limit(cfg.final_map_size)
    sequences, actor_rate = collect(cfg, batch, actor_steps, episode_steps)
    probe = Learner(cfg, device="cpu")
    replay = PrioritizedSequenceReplay(max(len(sequences), batch), cfg.window_len, cfg.seq_len,
                                       cfg.final_agents, hidden_dim(probe.model))
    for seq in sequences:
        replay.add(seq)
    samples = [replay.sample(batch, cfg.priority_beta) for _ in range(updates + 1)]
    print(f"{name:<10} {cfg.algo} model={cfg.model_preset:<5} {cfg.final_agents} agents "
          f"{cfg.final_map_size}x{cfg.final_map_size}, measured | actor {actor_rate:7.0f} "
          f"agent-steps/s, episodes of at most {episode_steps} steps, {len(sequences)} "
          f"sequences", flush=True)
    variants = dcc_masks if cfg.algo == "dcc" else ["recompute"]
    sensitive = sensitive and cfg.algo == "dcc"
    for variant in variants:
        if variant == "replay":
            maker = make_learner(cfg, sensitive)  # the weights time_learner starts from
            masks = [maker.causal_masks(s) for s in samples]
            with torch.no_grad():
                same = (float(maker.compute_loss(samples[0])[0]),
                        float(maker.compute_loss(samples[0], comm_masks=masks[0])[0]))
            pairs = sum(int(m.sum()) for m in masks)
            note = (f"masks by the target net before timing, {pairs / len(masks) / batch:.1f} "
                    f"requests per sequence; same loss on "
                    f"batch 0: recompute {same[0]:.6f} / replay {same[1]:.6f}")
        else:
            masks = [None] * len(samples)
            note = "causal masks recomputed in the unroll" if cfg.algo == "dcc" else ""
        r = time_learner(cfg, samples, masks, sensitive)
        print(f"  learner {variant:<9} batch {batch} x {updates} updates: "
              f"{r['wall']:6.3f} wall s/seq, {r['cpu']:6.3f} CPU s/seq, unrolled "
              f"{cfg.window_len} steps, {r['transitions']:8.1f} transitions/s, "
              f"paper batch {cfg.batch_size} -> {cfg.batch_size * r['wall']:6.1f} s/update"
              f"{'  (' + note + ')' if note else ''}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=2, help="timed updates (after a warm-up)")
    parser.add_argument("--batch", type=int, default=4, help="sequences per update (paper size)")
    parser.add_argument("--cpu-batch", type=int, default=32, help="sequences per update (CPU)")
    parser.add_argument("--actor-steps", type=int, default=16)
    parser.add_argument("--dcc-masks", nargs="+", choices=["recompute", "replay"],
                        default=["recompute", "replay"])
    parser.add_argument("--fresh-weights", action="store_true",
                        help="DCC: PyTorch's default init (hardly ever communicates) instead of "
                             "make_sensitive weights (communicates, like a trained network)")
    parser.add_argument("--episode-steps", type=int, default=0,
                        help="episode step limit of the played episodes (0: the preset's limit "
                             "at its final map size, 256 at 40x40). Short episodes make most "
                             "window steps padding, which the learner masks out")
    parser.add_argument("--only", nargs="*", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    names = ["dhc_paper", "dcc_paper", "dhc_cpu", "dcc_cpu"]
    for name in args.only or names:
        batch = args.batch if name.endswith("paper") else args.cpu_batch
        bench(name, batch, args.updates, args.actor_steps, args.dcc_masks,
              sensitive=not args.fresh_weights, episode_steps=args.episode_steps)
    print(f"reference learners (not measured here; {REFERENCE_SOURCE}), CPU s per sampled "
          f"sequence, paper networks:")
    for algo, ((low, high), what) in REFERENCES.items():
        print(f"  {algo}: {low:.2f}-{high:.2f} ({what}; trains 1 agent-0 transition per sequence)")


if __name__ == "__main__":
    main()
