"""DAgger's data and loss. Each episode is one shard `data/r{round}_e{index}.npz`: observations as
the policy saw them, bit-packed (for the "cost_to_go" observation its cost-to-go channel beside
them as int8 steps, `ctg`), positions, last-action inputs, labels (-1 = none) and the policy's
hidden state at every window start; written atomically. `LabelledData` holds the aggregate of
every round and indexes its labelled windows; `window_loss` unrolls one window (R2D2 burn-in)
and scores it against the labels."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import torch

from mapf_fleet.files import atomic_write
from mapf_fleet.grid.actions import STAY

from ..modelio import model_step
from ..replay import unpack_obs

# the per-episode counts a shard's manifest entry carries (summed into the run's counters)
SHARD_COUNTERS = ("labelled_states", "labels", "unsolved", "too_long", "expert_steps",
                  "label_seconds", "disagree", "disagree_off_goal", "off_goal_labels")


def shard_name(round_index: int, episode: int) -> str:
    return f"r{round_index:03d}_e{episode:03d}.npz"


def write_shard(path: Path, arrays: dict, meta: dict) -> None:
    def write(handle):
        np.savez_compressed(handle, **arrays, meta=np.array(json.dumps(meta)))

    atomic_write(path, write)


def read_shard(path: Path) -> tuple[dict, dict]:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files if k != "meta"}
        meta = json.loads(str(data["meta"]))
    return arrays, meta


def write_json(path: Path, data) -> None:
    atomic_write(path, lambda f: f.write((json.dumps(data, indent=1) + "\n").encode()))


def cap_wait_labels(labels: np.ndarray, cap: float, seed: int) -> np.ndarray:
    """`labels` (-1 = none) with wait labels dropped at random (seeded) until waits are at most
    `cap` of the labels left (MAPF-GPT keeps 20 %: a crowd's experts wait most of the time, and
    a policy trained on every wait learns to stand). cap >= 1 keeps every label."""
    if cap >= 1.0:
        return labels
    waits = np.flatnonzero(labels.ravel() == STAY)
    moves = int((labels >= 0).sum()) - len(waits)
    keep = int(np.floor(cap * moves / (1.0 - cap))) if cap > 0 else 0
    if len(waits) <= keep:
        return labels
    out = labels.copy()
    drop = np.random.default_rng(seed).choice(waits, size=len(waits) - keep, replace=False)
    out.reshape(-1)[drop] = -1
    return out


class LabelledData:
    """The aggregate: every shard's arrays in memory, and an index of labelled windows.
    wait_cap: the largest fraction of wait labels kept per episode (`cap_wait_labels`, seeded by
    the shard's name: the same labels every time it is loaded); the shards keep every label."""

    def __init__(self, seq_len: int, burn_in: int, wait_cap: float = 1.0):
        self.seq_len, self.burn_in = seq_len, burn_in
        self.wait_cap = float(wait_cap)
        self.episodes: list[dict] = []
        self.windows: list[tuple[int, int]] = []  # (episode, window j)
        self.names: set[str] = set()

    def add(self, name: str, arrays: dict) -> None:
        if name in self.names:
            return
        self.names.add(name)
        e = len(self.episodes)
        if self.wait_cap < 1.0:
            arrays = {**arrays, "labels": cap_wait_labels(arrays["labels"], self.wait_cap,
                                                          zlib.crc32(name.encode()))}
        self.episodes.append(arrays)
        labels = arrays["labels"]
        for j in range(len(arrays["hidden_starts"])):
            if (labels[j * self.seq_len:(j + 1) * self.seq_len] >= 0).any():
                self.windows.append((e, j))

    def window(self, e: int, j: int) -> dict:
        """Window j of episode e: steps [start, (j+1) L), the loss on [j L, (j+1) L)."""
        ep = self.episodes[e]
        start = int(ep["hidden_starts"][j])
        end = min(len(ep["labels"]), (j + 1) * self.seq_len)
        ctg = ep["ctg"][start:end] if "ctg" in ep else None
        return {"obs": unpack_obs(ep["obs_bits"][start:end], ctg),
                "positions": ep["positions"][start:end].astype(np.int64),
                "last": ep["last_actions"][start:end].astype(np.int64),
                "labels": ep["labels"][start:end].astype(np.int64),
                "burn": j * self.seq_len - start, "hidden": ep["hidden"][j].astype(np.float32)}


def unroll_window(model, algo: str, win: dict, device=None) -> torch.Tensor:
    """(L, N, 5) Q-values on the window's trained steps: the unroll from the stored hidden
    state, `burn` steps without gradient, then the trained steps."""
    t = lambda x: torch.as_tensor(x, device=device)  # noqa: E731
    obs, pos, last = t(win["obs"]), t(win["positions"]), t(win["last"])
    h = t(win["hidden"])[None]
    burn = win["burn"]
    with torch.no_grad():
        for s in range(burn):
            h = model_step(model, algo, obs[s][None], pos[s][None], h, last[s][None]).hidden
    qs = []
    for s in range(burn, len(obs)):
        out = model_step(model, algo, obs[s][None], pos[s][None], h, last[s][None])
        h = out.hidden
        qs.append(out.q[0])
    return torch.stack(qs)


def window_loss(model, algo: str, win: dict, device, loss: str, margin: float):
    """(summed loss over the labelled (step, agent) pairs, their count, agreements) of
    `unroll_window`'s Q-values against the window's labels."""
    from ..demos import cross_entropy_loss, margin_loss

    q = unroll_window(model, algo, win, device)  # (L, N, 5)
    labels = torch.as_tensor(win["labels"][win["burn"]:], device=device)
    mask = (labels >= 0).float()
    target = labels.clamp(min=0)
    count = mask.sum()
    if loss == "cross_entropy":
        value = cross_entropy_loss(q, target, mask) * count
    else:
        value = margin_loss(q, target, mask, margin) * count
    agree = ((q.argmax(-1) == target).float() * mask).sum()
    return value, float(count), float(agree)


