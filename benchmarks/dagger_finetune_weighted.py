"""An experiment, not a trainer: fine-tune a DAgger checkpoint offline on a run's aggregate with
the margin loss weighted per class of the labelled move (closer to the goal / stay / away), to
test whether weighting the expert's side-steps (the class a DAgger policy misses most,
`bench_dagger_agreement.py`) lifts the closed loop. The same windows, burn-in, wait cap (0.2),
margin (0.8), learning rate (1e-4), batch (8 windows) and gradient clip (40) as
`mapf-fleet dagger` (`training.dagger.driver.Dagger.train`); seed 0.

    .venv/bin/python benchmarks/dagger_finetune_weighted.py CHECKPOINT RUN_DIR OUT.pt
        [--updates 300] [--weights 1,1,4]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from mapf_fleet.coordination.ranking import distance_classes
from mapf_fleet.models.checkpoint import OPTIONAL_FIELDS, REQUIRED_FIELDS, load_checkpoint, save_checkpoint
from mapf_fleet.training.dagger.data import LabelledData, read_shard, unroll_window
from mapf_fleet.training.demos import margin_loss

MARGIN, LR, BATCH, CLIP, WAIT_CAP = 0.8, 1e-4, 8, 40.0, 0.2


def weighted_window_loss(model, algo, win, weights):
    """(the window's summed weighted margin loss, its weight, agreements, labels)."""
    q = unroll_window(model, algo, win)
    labels = torch.as_tensor(win["labels"][win["burn"]:]).long()
    have = (labels >= 0).float()
    target = labels.clamp(min=0)
    classes = torch.as_tensor(distance_classes(win["obs"][win["burn"]:]))
    w = weights[classes.gather(-1, target[..., None])[..., 0]] * have
    agree = float(((q.argmax(-1) == target).float() * have).sum())
    # margin_loss is the mean over its mask: weights as the mask give the weighted mean
    return margin_loss(q, target, w, MARGIN) * w.sum(), float(w.sum()), agree, float(have.sum())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("run_dir")
    p.add_argument("out")
    p.add_argument("--updates", type=int, default=300)
    p.add_argument("--weights", default="1,1,4", help="closer,stay,away (default 1,1,4)")
    args = p.parse_args()
    torch.set_num_threads(1)
    weights = torch.tensor([float(x) for x in args.weights.split(",")] + [1.0])
    if len(weights) != 4:
        raise SystemExit(f"--weights: three values closer,stay,away, got {args.weights!r}")
    model, meta = load_checkpoint(args.checkpoint)
    algo = meta.get("algo") or meta.get("model_config", {}).get("algo")
    data = LabelledData(16, 8, WAIT_CAP)
    for shard in sorted(Path(args.run_dir, "data").glob("r*_e*.npz")):
        data.add(shard.stem, read_shard(shard)[0])
    optimizer = torch.optim.Adam(model.parameters(), lr=LR)
    rng = np.random.default_rng(0)
    model.train()
    began, log = time.time(), []
    for u in range(args.updates):
        wins = [data.window(*data.windows[k]) for k in rng.integers(len(data.windows), size=BATCH)]
        optimizer.zero_grad(set_to_none=True)
        loss_sum = weight_sum = agree_sum = count = 0.0
        for win in wins:
            loss, w, agree, n = weighted_window_loss(model, algo, win, weights)
            loss.backward()
            loss_sum, weight_sum = loss_sum + float(loss.detach()), weight_sum + w
            agree_sum, count = agree_sum + agree, count + n
        for param in model.parameters():
            if param.grad is not None:
                param.grad /= max(weight_sum, 1.0)
        torch.nn.utils.clip_grad_norm_(model.parameters(), CLIP)
        optimizer.step()
        log.append((loss_sum / max(weight_sum, 1.0), agree_sum / max(count, 1.0)))
        if (u + 1) % 100 == 0:
            loss_mean, agree_mean = np.mean(log[-100:], axis=0)
            print(f"update {u + 1}: weighted loss {loss_mean:.3f}, agreement {agree_mean:.3f}, "
                  f"{time.time() - began:.0f} s", flush=True)
    model.eval()
    keep = set(REQUIRED_FIELDS) | set(OPTIONAL_FIELDS)
    save_checkpoint(args.out, model, {k: v for k, v in meta.items() if k in keep})
    print(f"saved {args.out}")


if __name__ == "__main__":
    main()
