"""The learner: n-step double-network Q-learning over replayed sequences of every agent.

Efficiency choice (vs the reference learner). The reference samples one transition of agent 0,
replays up to 16 steps of *every* agent to rebuild agent 0's recurrent and communication state,
and trains agent 0's single output; all other outputs are thrown away. Here a sample is a
sequence of `seq_len` steps of one episode and the loss covers **every agent at every trained
step** (R2D2-style stored hidden state + optional burn-in). The forward cost per sample is about
the same as the reference's (all agents over burn_in + seq_len + n steps, online and target),
but it trains seq_len x N agent-transitions instead of 1. Approximations, both standard:
  - the hidden state at the start of a window is the one the actor stored (with the actor's,
    slightly older, weights); `burn_in` steps without a loss let it adapt (R2D2);
  - one priority per sequence, eta * max|td| + (1 - eta) * mean|td| over its agents and steps,
    and one importance weight per sequence (R2D2).
Every agent is trained; actors explore with epsilon on agent 0 only, as the reference does
(`explore_all_agents`, see TrainConfig: with every agent exploring the policy learns to wait).

DCC decision-causal masks: by default the learner *recomputes* them with the network being
unrolled (the online net for Q(s, a), the target net for the bootstrap) instead of replaying the
masks the actor recorded. Decided so because (1) at inference, in the evaluator and on the fleet, the masks always
come from the acting weights, so recomputing trains exactly the function that is deployed;
(2) the bootstrap max_a Q_target(o_{t+n}, a) has to be the target network's own greedy value,
which includes its own communication choice, and the actor never recorded a mask for the final
observation of a time-limited episode; (3) replayed masks are stale by the actor's weight lag plus
the sequence's age in replay, so the online net would be fitted on communication graphs it would
no longer choose. The price is the causal check (one extra pass per FOV neighbour) in every
learner step. `update(batch, comm_masks=...)` replays recorded masks instead (behaviour-policy
masks, as the reference learner does; both unrolls use them, the bootstrap included): cheaper,
but the actor does not record masks yet (see benchmarks/bench_training.py for the cost of each).
Window steps outside the episode (burn-in before its start, n-step padding after its end) are
masked out of each step (`_step_agents`): their padded agents all stand on one cell, and the
causal check used to run on every pair of them (several times the CPU per sequence on short
episodes, the same loss: docs/results.md, "Performance").

Correctness of the alignment (obs/action/reward/next obs, stored hidden + burn-in, padding of
short sequences, terminal cut, time-limit bootstrap) is checked against an independent
full-episode unroll in test/test_training_learner.py.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn.functional as F

from mapf_fleet.models.policy import resolve_device

from .config import TrainConfig
from .modelio import build_model, model_step
from .replay import FAR_AWAY, SequenceBatch


class Learner:
    def __init__(self, cfg: TrainConfig, device: str | torch.device | None = None):
        self.cfg = cfg
        self.device = resolve_device(cfg.device) if device is None else torch.device(device)
        self.model = build_model(cfg).to(self.device)
        self.target = copy.deepcopy(self.model).eval()
        for p in self.target.parameters():
            p.requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.updates = 0

    # ------------------------------------------------------------------------------------------
    def _tensors(self, batch: SequenceBatch, comm_masks=None) -> dict:
        # Agents are packed at the front of a slot: cut the padding of small settings.
        n = int(np.flatnonzero(batch.agent_mask.any(0)).max()) + 1
        dev = self.device

        def t(x, dtype=None):
            return torch.as_tensor(np.ascontiguousarray(x), device=dev, dtype=dtype)

        masks = None
        if comm_masks is not None:
            if self.cfg.algo != "dcc":
                raise ValueError("comm_masks: only the DCC learner replays communication masks")
            shape = batch.positions.shape[:3] + batch.positions.shape[2:3]
            if tuple(np.shape(comm_masks)) != shape:
                raise ValueError(f"comm_masks: expected shape (B, W, N, N) = {shape}, "
                                 f"got {tuple(np.shape(comm_masks))}")
            masks = t(np.asarray(comm_masks)[:, :, :n, :n], torch.bool)
        return {
            "comm_masks": masks,
            "obs": t(batch.obs[:, :, :n]), "positions": t(batch.positions[:, :, :n]),
            "last": t(batch.last_actions[:, :, :n]), "actions": t(batch.actions[:, :, :n]),
            "returns": t(batch.returns[:, :, :n]), "discount": t(batch.boot_discount),
            "boot_index": t(batch.boot_index), "step_mask": t(batch.step_mask),
            "agent_mask": t(batch.agent_mask[:, :n]), "start": t(batch.start_index),
            "hidden": t(batch.hidden[:, :n]), "weights": t(batch.weights),
        }

    @staticmethod
    def _step_agents(d: dict, w: int) -> torch.Tensor:
        """(B, N) agents that exist at window step w: the sequence's agents, minus the padding
        steps before an episode's start or after its end (positions FAR_AWAY there). Their
        outputs are never used (the stored hidden replaces the carried one before the start; no
        loss or bootstrap reads past the end), but unmasked they all stood on one cell, each in
        every other's FOV, and DCC ran its causal check on every pair of them."""
        return d["agent_mask"] & (d["positions"][:, w, :, 0] != FAR_AWAY)

    def _unroll(self, net, d: dict, w_from: int, w_to: int, h: torch.Tensor,
                comm_masks_out: list | None = None):
        """Run `net` over window steps [w_from, w_to); the stored hidden state replaces the
        carried one until each sample's own start index. `comm_masks_out`: a list that gets each
        step's communication mask (B, N, N)."""
        qs = []
        for w in range(w_from, w_to):
            mask = None if d["comm_masks"] is None else d["comm_masks"][:, w]
            out = model_step(net, self.cfg.algo, d["obs"][:, w], d["positions"][:, w], h,
                             d["last"][:, w], self._step_agents(d, w), comm_mask=mask)
            before_start = (d["start"] > w)[:, None, None]  # input of step w+1 still stored
            h = torch.where(before_start, d["hidden"], out.hidden)
            qs.append(out.q)
            if comm_masks_out is not None:
                comm_masks_out.append(out.comm_mask)
        return torch.stack(qs, 1), h

    @torch.no_grad()
    def causal_masks(self, batch: SequenceBatch, net: torch.nn.Module | None = None
                     ) -> np.ndarray:
        """bool (B, W, N, N): the DCC decision-causal masks that `net` (default: the target
        network) chooses at every window step when unrolled as the learner unrolls it, i.e.
        what an actor acting with those weights would have recorded. For tests and benchmarks
        of `comm_masks` (the actor does not record masks)."""
        if self.cfg.algo != "dcc":
            raise ValueError("causal_masks: only DCC has decision-causal masks")
        d = self._tensors(batch)
        steps: list[torch.Tensor] = []
        self._unroll(self.target if net is None else net, d, 0, d["obs"].shape[1], d["hidden"],
                     comm_masks_out=steps)
        n_slots, n = batch.positions.shape[2], d["obs"].shape[2]
        masks = np.zeros(batch.positions.shape[:2] + (n_slots, n_slots), bool)
        masks[:, :, :n, :n] = torch.stack(steps, 1).cpu().numpy()
        return masks

    def q_and_targets(self, batch: SequenceBatch, d: dict | None = None, comm_masks=None):
        """Online Q of the taken actions (B, L, N) (with autograd), n-step targets (B, L, N)
        and the loss mask (B, L, N) float: what the loss compares, exposed for tests.
        `comm_masks` (B, W, N, N) bool, DCC only: recorded decision-causal masks of every
        window step, replayed by both the online and the target unroll (None: recomputed)."""
        cfg = self.cfg
        d = self._tensors(batch, comm_masks) if d is None else d
        burn, length, window = cfg.burn_in, cfg.seq_len, cfg.window_len
        h0 = d["hidden"]
        with torch.no_grad():
            q_target, _ = self._unroll(self.target, d, 0, window, h0)  # (B, W, N, 5)
            values = q_target.max(-1).values  # (B, W, N)
            n_agents = values.shape[-1]
            index = d["boot_index"][:, :, None].expand(-1, -1, n_agents)
            boot = values.gather(1, index)  # (B, L, N)
            target = d["returns"] + d["discount"][:, :, None] * boot
            h = h0
            if burn:
                _, h = self._unroll(self.model, d, 0, burn, h0)
        q_online, _ = self._unroll(self.model, d, burn, burn + length, h)  # (B, L, N, 5)
        q_taken = q_online.gather(-1, d["actions"][..., None]).squeeze(-1)
        mask = (d["step_mask"][:, :, None] & d["agent_mask"][:, None, :]).float()
        self._last_q_online = q_online  # the margin loss of demo updates needs every action
        return q_taken, target, mask

    def compute_loss(self, batch: SequenceBatch, demo_weight: float = 0.0,
                     demo_margin: float = 0.8, comm_masks=None, demo_loss: str = "margin"):
        """Return (loss, per-sequence priorities (B,) numpy, stats dict). With demo_weight > 0
        the batch holds demonstrations and a supervised loss on its actions is used:
        `demo_loss` "margin" adds the DQfD margin loss to the TD loss, "cross_entropy"
        (behaviour cloning) replaces the TD loss by the cross-entropy of softmax(Q).
        `comm_masks`: see `q_and_targets` (None, the default, recomputes the DCC masks)."""
        cfg, d = self.cfg, self._tensors(batch, comm_masks)
        q_taken, target, mask = self.q_and_targets(batch, d)
        td = target - q_taken
        elementwise = F.huber_loss(q_taken, target, reduction="none", delta=cfg.huber_delta)
        count = mask.sum().clamp(min=1.0)
        loss = (elementwise * mask * d["weights"][:, None, None]).sum() / count
        with torch.no_grad():
            abs_td = td.abs() * mask
            per_seq_max = abs_td.flatten(1).max(1).values
            per_seq_mean = abs_td.flatten(1).sum(1) / mask.flatten(1).sum(1).clamp(min=1.0)
            priorities = cfg.priority_eta * per_seq_max + (1 - cfg.priority_eta) * per_seq_mean
            mean_q = (q_taken * mask).sum() / count
        stats = {"loss": float(loss.detach()), "mean_q": float(mean_q),
                 "mean_abs_td": float(abs_td.sum() / count), "transitions": int(mask.sum())}
        if demo_weight > 0:
            from .demos import margin_loss

            q_online = self._last_q_online
            stats["td_loss"] = stats["loss"]
            if demo_loss == "cross_entropy":
                from .demos import cross_entropy_loss

                supervised = cross_entropy_loss(q_online, d["actions"], mask)
                stats["cross_entropy"] = float(supervised.detach())
                loss = demo_weight * supervised
            elif demo_loss == "margin":
                supervised = margin_loss(q_online, d["actions"], mask, demo_margin)
                stats["margin_loss"] = float(supervised.detach())
                loss = loss + demo_weight * supervised
            else:
                raise ValueError(f"demo_loss must be 'margin' or 'cross_entropy', got {demo_loss!r}")
            with torch.no_grad():
                agree = (q_online.argmax(-1) == d["actions"]).float()
                stats["demo_agreement"] = float((agree * mask).sum() / count)
            stats["loss"] = float(loss.detach())
        self._last_q_online = None
        return loss, priorities.cpu().numpy(), stats

    def update(self, batch: SequenceBatch, demo_weight: float = 0.0, demo_margin: float = 0.8,
               comm_masks=None, demo_loss: str = "margin"):
        """One gradient step; returns (priorities, stats). `comm_masks`: see `q_and_targets`."""
        self.model.train()
        loss, priorities, stats = self.compute_loss(batch, demo_weight, demo_margin, comm_masks,
                                                    demo_loss)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        stats["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(self.model.parameters(),
                                                                   self.cfg.grad_clip))
        self.optimizer.step()
        self.updates += 1
        if self.updates % self.cfg.target_update_interval == 0:
            self.sync_target()
        return priorities, stats

    def sync_target(self) -> None:
        self.target.load_state_dict(self.model.state_dict())

    def cpu_weights(self) -> dict:
        return {k: v.detach().to("cpu").clone() for k, v in self.model.state_dict().items()}

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "target": self.target.state_dict(),
                "optimizer": self.optimizer.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.target.load_state_dict(state["target"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])
