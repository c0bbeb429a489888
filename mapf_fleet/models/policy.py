"""LearnedPolicy: a DHC or DCC network acting for B episodes x N agents (evaluator, actors).

It keeps the recurrent state between calls: the hidden vectors (the post-communication hidden
of the previous step) and, for DCC, the last actions (-1 before the first step). The caller
builds the observations the model reads, `policy.observation` (`EnvConfig(observation=...)`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from mapf_fleet.grid.actions import NUM_ACTIONS


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """The torch device for `device`, the one reading of a device name for the fleet's policy
    processes, the evaluator and the trainers: auto is cuda when torch sees a CUDA device, else
    cpu; cpu, cuda and cuda:N as torch reads them. ValueError (one line) for an unknown name or
    for cuda where torch sees none."""
    if isinstance(device, torch.device):
        return device
    available = torch.cuda.is_available()
    if device == "auto":
        return torch.device("cuda" if available else "cpu")
    try:
        found = torch.device(device)
    except (RuntimeError, TypeError):
        found = None
    if found is None or found.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {device!r}")
    if found.type == "cuda" and not available:
        raise ValueError(f"device is {device}, but torch sees no CUDA device here "
                         "(torch.cuda.is_available() is false): use device auto or cpu")
    return found


DEVICE_HELP = "auto (cuda when torch sees a CUDA device, else cpu), cpu, cuda or cuda:N"


def device_arg(value: str) -> str:
    """argparse type of a --device option: `value` when `resolve_device` reads it, else the
    one-line refusal."""
    import argparse

    try:
        resolve_device(value)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return value


class LearnedPolicy:
    def __init__(self, model: nn.Module, device: str | torch.device = "auto"):
        self.device = resolve_device(device)
        self.model = model.to(self.device).eval()
        self.algo = model.config.algo
        # what the caller's environment must build: "paper" or "cost_to_go" (grid.env)
        self.observation = model.config.observation
        self.hidden: torch.Tensor | None = None
        self.last_actions: torch.Tensor | None = None
        self.q_values: np.ndarray | None = None  # (B, N, 5) of the last `act`
        self.comm_mask: np.ndarray | None = None  # (B, N, N) of the last `act`

    @property
    def num_envs(self) -> int:
        return 0 if self.hidden is None else self.hidden.shape[0]

    @property
    def num_agents(self) -> int:
        return 0 if self.hidden is None else self.hidden.shape[1]

    def reset(self, num_envs: int, num_agents: int) -> None:
        """Start new episodes in all environments."""
        if num_envs < 1 or num_agents < 1:
            raise ValueError(f"reset: num_envs and num_agents must be >= 1, "
                             f"got {num_envs}, {num_agents}")
        self.hidden = torch.zeros(num_envs, num_agents, self.model.config.hidden_dim,
                                  device=self.device)
        self.last_actions = torch.full((num_envs, num_agents), -1, dtype=torch.long,
                                       device=self.device)
        self.q_values = self.comm_mask = None

    def reset_env(self, env_index: int) -> None:
        """Start a new episode in one environment (the others keep their state)."""
        if self.hidden is None:
            raise RuntimeError("reset_env: call reset(num_envs, num_agents) first")
        self.hidden[env_index] = 0.0
        self.last_actions[env_index] = -1

    @torch.no_grad()
    def act(self, obs, positions, greedy: bool = True, epsilon=0.0,
            rng: np.random.Generator | None = None, agent_mask=None) -> np.ndarray:
        """Actions (B, N) int64 for obs (B, N, C, fov, fov) and positions (B, N, 2); C = 6, 7
        for the "cost_to_go" observation (`self.observation`).

        A single episode may be given without the B axis (obs (N, ...), positions (N, 2));
        actions are then (N,). greedy=True takes argmax Q (lowest action on ties); otherwise
        epsilon-greedy with `epsilon` (a float or an array broadcastable to (B, N)) and `rng`.
        The first call after construction resets to the shapes of `obs`.
        """
        obs = np.asarray(obs, dtype=np.float32)
        positions = np.asarray(positions)
        single = obs.ndim == 4
        if single:
            obs, positions = obs[None], positions[None]
            agent_mask = None if agent_mask is None else np.asarray(agent_mask)[None]
        channels = self.model.config.obs_shape[0]
        if obs.ndim == 5 and obs.shape[2] != channels:
            raise ValueError(f"act: obs has {obs.shape[2]} channels, the model reads the "
                             f"{self.observation!r} observation ({channels} channels): build it "
                             f"with EnvConfig(observation={self.observation!r})")
        batch, num_agents = obs.shape[:2]
        if self.hidden is None:
            self.reset(batch, num_agents)
        if (batch, num_agents) != (self.num_envs, self.num_agents):
            raise ValueError(f"act: obs has {batch} envs x {num_agents} agents but the policy was "
                             f"reset for {self.num_envs} x {self.num_agents}")
        kwargs = {}
        if self.algo == "dcc":
            kwargs["last_action"] = self.last_actions
        out = self.model.step(torch.from_numpy(obs).to(self.device),
                              torch.from_numpy(positions.astype(np.int64)).to(self.device),
                              self.hidden, agent_mask=agent_mask, **kwargs)
        actions = out.q.argmax(-1)
        if not greedy:
            actions = self._explore(actions, epsilon, rng)
        self.hidden = out.hidden
        self.last_actions = actions
        self.q_values = out.q.cpu().numpy()
        self.comm_mask = out.comm_mask.cpu().numpy()
        result = actions.cpu().numpy()
        return result[0] if single else result

    def set_last_actions(self, actions) -> None:
        """Replace the last actions (B, N) (or (N,)) with what was really executed, e.g. by the
        coordination layer: DCC's next step reads them as its last-action input."""
        if self.last_actions is None:
            raise RuntimeError("set_last_actions: call reset(num_envs, num_agents) first")
        actions = torch.as_tensor(np.asarray(actions, dtype=np.int64), device=self.device)
        self.last_actions = actions.reshape(self.last_actions.shape)

    def _explore(self, actions: torch.Tensor, epsilon, rng) -> torch.Tensor:
        rng = rng if rng is not None else np.random.default_rng()
        epsilon = np.broadcast_to(np.asarray(epsilon, dtype=np.float64), tuple(actions.shape))
        if ((epsilon < 0) | (epsilon > 1)).any():
            raise ValueError(f"act: epsilon must be in [0, 1], got {epsilon}")
        explore = rng.random(actions.shape) < epsilon
        random_actions = rng.integers(0, NUM_ACTIONS, size=actions.shape)
        chosen = np.where(explore, random_actions, actions.cpu().numpy())
        return torch.from_numpy(chosen).to(actions.device)
