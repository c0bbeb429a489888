"""Where a DAgger checkpoint disagrees with its labels: the labels of a run's shards against the
checkpoint's argmax, by the distance class of each move (closer to the goal / stay / away), and
on the states with two closer moves whether the network's Q picks the labelled one of the two.

Each window is unrolled as in training (`training.dagger.data.LabelledData`, R2D2 burn-in from the
hidden state stored in the shard), every label counted (no wait cap: the shards' labels as the
labeller gave them).

    .venv/bin/python benchmarks/bench_dagger_agreement.py CHECKPOINT RUN_DIR [--round K]
        [--episodes N]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from mapf_fleet.coordination.ranking import distance_classes
from mapf_fleet.models.checkpoint import load_checkpoint
from mapf_fleet.training.dagger.data import LabelledData, read_shard, unroll_window

CLASSES = ("closer", "stay", "away", "blocked")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("run_dir")
    p.add_argument("--round", type=int, default=None,
                   help="the shards of this round (default: the last round with shards)")
    p.add_argument("--episodes", type=int, default=8, help="shards read (default 8)")
    args = p.parse_args()
    torch.set_num_threads(1)
    model, meta = load_checkpoint(args.checkpoint)
    model.eval()
    algo = meta.get("algo") or meta.get("model_config", {}).get("algo")
    shards = sorted(Path(args.run_dir, "data").glob("r*_e*.npz"))
    if not shards:
        raise SystemExit(f"{args.run_dir}/data: no shards")
    rnd = args.round if args.round is not None else max(int(s.stem[1:4]) for s in shards)
    shards = [s for s in shards if int(s.stem[1:4]) == rnd][:args.episodes]
    data = LabelledData(16, 8)
    for s in shards:
        data.add(s.stem, read_shard(s)[0])
    confusion = np.zeros((4, 4), np.int64)  # label class x argmax class
    pairs = pairs_right = agree_total = 0
    with torch.no_grad():
        for e, j in data.windows:
            win = data.window(e, j)
            q = unroll_window(model, algo, win).numpy()
            labels = win["labels"][win["burn"]:]
            classes = distance_classes(win["obs"][win["burn"]:])
            have = labels >= 0
            label_class = np.take_along_axis(classes, np.clip(labels, 0, 4)[..., None], -1)[..., 0]
            argmax = q.argmax(-1)
            agree_total += int(((argmax == labels) & have).sum())
            argmax_class = np.take_along_axis(classes, argmax[..., None], -1)[..., 0]
            np.add.at(confusion, (label_class[have], argmax_class[have]), 1)
            two = have & (label_class == 0) & ((classes == 0).sum(-1) == 2)
            for idx in zip(*np.nonzero(two)):
                closer = np.nonzero(classes[idx] == 0)[0]
                pairs += 1
                pairs_right += int(closer[np.argmax(q[idx][closer])] == labels[idx])
    total = int(confusion.sum())
    print(f"{args.checkpoint} on {len(shards)} shards of round {rnd} of {args.run_dir}: "
          f"{total} labels")
    print("| label \\ argmax | " + " | ".join(CLASSES[:3]) + " | labels | recall |")
    print("|---|" + "---:|" * 5)
    for c in range(3):
        row = confusion[c]
        if not row.sum():
            continue
        print(f"| {CLASSES[c]} | " + " | ".join(str(int(x)) for x in row[:3])
              + f" | {int(row.sum())} | {row[c] / row.sum():.2f} |")
    print(f"agreement (argmax = label): {agree_total / max(total, 1):.3f}")
    print(f"two closer moves, one labelled: the network's Q prefers it in {pairs_right} of {pairs} "
          f"({pairs_right / max(pairs, 1):.2f}; 0.50 = chance)")


if __name__ == "__main__":
    main()
