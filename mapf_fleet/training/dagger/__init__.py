"""DAgger behind the fleet's arbiter: roll the policy out under the PIBT shield, have the expert
(LaCAM) label every agent's next move at the visited joint states, aggregate, retrain, repeat.

    mapf-fleet dagger --config config/training/dagger_dcc.yaml --run-dir runs/dagger_dcc
    mapf-fleet dagger --run-dir runs/dagger_dcc          # resume (after a stop or kill -9)

Round k (k = 0, 1, ...):
  1. collect (`rollout.py`, `labeller.py`): `episodes_per_round` episodes drawn from the task
     list (`tasks`, plus `late_tasks` from round `late_tasks_from`), each played by the round's
     policy (the init checkpoint in round 0, else round k-1's weights) under `conflict_rule` (PIBT with
     the anchor by default, the fleet's arbiter) with its Q-values ranked by `ranking`. At
     every `label_interval`-th step (backing off after states it cannot label,
     `label_backoff_max`) the labeller labels the joint state (`labeller`: "lacam" as follows,
     "committed": the next move of one kept plan, or "stuck": that plan's moves from the state
     where the rollout stopped progressing, `labeller.py`): LaCAM (pymapf,
     `coordination.planners.ClassicalPlanner`, `label_time_limit` seconds per connected region)
     from the agents' current cells to their goals; the label of agent i is the first move of its
     plan. DAgger's mixing: with probability beta_k = `beta0` * `beta_decay`^k (per labelled
     step) the shield executes the expert's ranking (its move first, then the distance order)
     instead of the policy's. A state is skipped (no labels; counted) when LaCAM leaves any agent
     unplanned within the limit ("unsolved") or when its plan is far longer than needed
     ("too_long": makespan > min(the task's step limit, `max_plan_factor` x the longest BFS
     distance of any agent to its goal + `max_plan_slack`)): a first-found plan many times longer
     than needed spends its first moves wandering, a poor label (docs/results.md, "DAgger behind
     the arbiter"). Episodes are
     played by `num_workers` workers of the shared worker pool (`training/ray_pool.py`: Ray
     actors, a local Ray with `num_cpus` or `ray_address`, or in-process with `use_ray: false`).
     The driver waits while they play: collection and training never run at the same time, so a
     run uses about `num_cpus` cores.
  2. aggregate (`data.py`): each episode is one shard `data/r{round}_e{index}.npz`, recorded in
     `data/manifest.json` after its file; both written atomically.
  3. train (`data.py`): `updates_per_round` updates on the aggregate of every round so far
     (DAgger). An update takes `batch_windows` windows sampled uniformly from all labelled
     windows: window j of an episode trains steps [j L, (j+1) L) (L = `seq_len`), unrolled from
     the hidden state the policy had at step j L - `burn_in` through `burn_in` steps without a
     loss (R2D2). The network sees exactly its inputs along the rollout (observations, positions,
     executed last actions: DCC's recurrent input is the executed move, as in the fleet). Loss on
     every agent of every labelled step: `loss` "cross_entropy" (softmax over the Q-head as
     logits) or "margin" (the DQfD large-margin loss of `training.demos.margin_loss`).
  4. checkpoint `checkpoints/round_{k}.pt` (the checkpoint format, atomic; metadata: round,
     labels, CPU seconds, `rankings` {conflict_rule: ranking}: the ranking it runs with by default)
     and the training state, then the held-out check: `heldout` settings, `heldout_count`
     generated instances each (seeded apart from training; never the published test sets),
     success and average steps under the shield, appended to `curve.json` / `curve.csv` and
     TensorBoard (`tb/`). Before round 0 the same check runs on the init checkpoint (round -1)
     and on plain PIBT (the distance ranking, no network). `driver.py` runs the rounds and
     resumes them; `report.py` compares finished runs.

Expert ceiling (`--expert-ceiling`, `ceiling.py`): the configured labeller as the policy under
the configured rule beside plain PIBT (success, steps, lifelong throughput, self-agreement, CPU
seconds per label): the most a policy imitating it could reach.

Observation (`observation`): the init checkpoint's unless set; "cost_to_go" on a "paper"
checkpoint adds the normalised cost-to-go channel (`grid.env.cost_to_go_channel`), warm-started
with that channel's first-conv weights zero (`models.checkpoint.with_observation`); the round
checkpoints record it in their `model_config`. CUDA is used when present (`device: auto`);
nothing needs it.
"""

from .config import LOSSES, DaggerConfig, DaggerConfigError, config_from_dict, load_config
from .data import LabelledData, read_shard, shard_name, window_loss, write_shard
from .driver import (CHECKPOINT_DIR, CONFIG_FILE, CURVE_CSV, CURVE_JSON, DATA_DIR, MANIFEST,
                     STATE_JSON, STATE_PT, Dagger)
from .ceiling import expert_ceiling
from .labeller import (LABELLERS, CommittedLabeller, LabelState, Labeller, Labels, LaCAMLabeller,
                       make_labeller)
from .report import compare_runs, plot_runs
from .rollout import (DaggerWorker, make_instance, play_episode, play_lifelong, play_plain_pibt,
                      window_starts)


def main(argv: list[str] | None = None) -> int:
    """`mapf-fleet dagger` (dagger/cli.py)."""
    from .cli import main as cli_main

    return cli_main(argv)


__all__ = ["CHECKPOINT_DIR", "CONFIG_FILE", "CURVE_CSV", "CURVE_JSON", "DATA_DIR", "LABELLERS",
           "LOSSES", "MANIFEST", "CommittedLabeller", "expert_ceiling", "play_lifelong", "STATE_JSON", "STATE_PT", "Dagger", "DaggerConfig", "DaggerConfigError",
           "DaggerWorker", "LaCAMLabeller", "LabelState", "LabelledData", "Labeller", "Labels",
           "compare_runs", "config_from_dict", "load_config", "main", "make_instance",
           "make_labeller", "play_episode", "play_plain_pibt", "plot_runs", "read_shard",
           "shard_name", "window_loss", "window_starts", "write_shard"]
