"""DHC network (Ma, Luo and Ma 2021) as in the paper's appendix and the reference code.

One step of agent i:
  h_i   = GRU(encoder(obs_i), hidden_i)                    (encode)
  for each of `comm_rounds` rounds (one shared attention + GRU):
    if i has partners P_i (the k nearest agents inside its FOV, see comm.dhc_partners):
      h_i <- GRU_u(attention(query h_i, keys/values [h_i] + [h_j for j in P_i]), h_i)
    (agents without partners keep h_i; every agent's current h_i is what its partners read)
  q_i   = dueling(h_i)
The hidden carried to the next step is the post-communication h_i (as the reference).

The batched `step` (evaluator, trainer) and the fleet's exchange (`models.exchange`: the robots
of one process, with the vectors they received) share the pieces `encode_batch`, `round_batch`
and `head`, which take each receiver's gathered member vectors, so both compute the same
numbers.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .comm import dhc_partners_torch
from .common import DuelingHead, StepOutput, as_float, as_long, check_batch_inputs, module_device
from .config import DHC_SQUEEZE_CHANNELS, ModelConfig


class ResBlock(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.block1 = nn.Conv2d(channels, channels, 3, 1, 1)
        self.block2 = nn.Conv2d(channels, channels, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.block2(F.relu(self.block1(x))) + x)


class DHCAttention(nn.Module):
    """Multi-head attention of the reference: Q, K, V per head, W_O back to one head's width."""

    def __init__(self, hidden_dim: int, num_heads: int, head_dim: int):
        super().__init__()
        self.num_heads, self.head_dim = num_heads, head_dim
        self.W_Q = nn.Linear(hidden_dim, num_heads * head_dim)
        self.W_K = nn.Linear(hidden_dim, num_heads * head_dim)
        self.W_V = nn.Linear(hidden_dim, num_heads * head_dim)
        self.W_O = nn.Linear(num_heads * head_dim, head_dim, bias=False)

    def forward(self, query_h: torch.Tensor, member_h: torch.Tensor,
                member_valid: torch.Tensor) -> torch.Tensor:
        """query_h (M, H), member_h (M, S, H), member_valid (M, S) -> (M, head_dim)."""
        m, s, _ = member_h.shape
        q = self.W_Q(query_h).view(m, 1, self.num_heads, self.head_dim)
        k = self.W_K(member_h).view(m, s, self.num_heads, self.head_dim)
        v = self.W_V(member_h).view(m, s, self.num_heads, self.head_dim)
        scores = (q * k).sum(-1) / math.sqrt(self.head_dim)  # (M, S, heads)
        scores = scores.masked_fill(~member_valid[:, :, None], float("-inf"))
        weights = torch.softmax(scores, dim=1)
        context = (weights[..., None] * v).sum(1)  # (M, heads, head_dim)
        return self.W_O(context.reshape(m, self.num_heads * self.head_dim))


class DHCNetwork(nn.Module):
    algo = "dhc"

    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        config = config if config is not None else ModelConfig.preset("dhc", "paper")
        if config.algo != "dhc":
            raise ValueError(f"DHCNetwork: config.algo must be 'dhc', got {config.algo!r}")
        self.config = config
        channels = config.conv_channels[0]
        side = config.fov - 2  # one valid 3x3 conv; the residual blocks keep the size
        self.obs_encoder = nn.Sequential(
            nn.Conv2d(config.obs_shape[0], channels, 3, 1),  # 6 channels, 7 with cost_to_go
            nn.ReLU(True),
            ResBlock(channels),
            ResBlock(channels),
            ResBlock(channels),
            nn.Conv2d(channels, DHC_SQUEEZE_CHANNELS, 1, 1),
            nn.ReLU(True),
            nn.Flatten(),
        )
        self.latent_dim = DHC_SQUEEZE_CHANNELS * side * side
        # Channels-last weights and inputs: oneDNN's CPU convolutions are faster in that layout
        # (docs/results.md, "Performance (2-core machine, no GPU)"); load_state_dict keeps it.
        self.obs_encoder.to(memory_format=torch.channels_last)
        self.recurrent = nn.GRUCell(self.latent_dim, config.hidden_dim)
        self.attention = DHCAttention(config.hidden_dim, config.num_heads, config.head_dim)
        self.update = nn.GRUCell(config.head_dim, config.hidden_dim)
        self.head = DuelingHead(config.hidden_dim)

    @property
    def hidden_dim(self) -> int:
        return self.config.hidden_dim

    # ---- shared pieces ------------------------------------------------------------------

    def encode_batch(self, obs: torch.Tensor, hidden: torch.Tensor) -> torch.Tensor:
        """obs (M, C, fov, fov) (C = config.obs_shape[0]), hidden (M, H) -> (M, H)."""
        features = self.obs_encoder(obs.contiguous(memory_format=torch.channels_last))
        return self.recurrent(features, hidden)

    def round_batch(self, query_h: torch.Tensor, member_h: torch.Tensor,
               member_valid: torch.Tensor) -> torch.Tensor:
        """One communication round for receivers that have at least one partner."""
        return self.update(self.attention(query_h, member_h, member_valid), query_h)

    # ---- batched ------------------------------------------------------------------------

    def step(self, obs, positions, hidden=None, agent_mask=None, partners=None) -> StepOutput:
        """One step of B episodes x N agents (differentiable; wrap in torch.no_grad to act).

        obs (B, N, C, fov, fov) (C = config.obs_shape[0]), positions (B, N, 2) int, hidden
        (B, N, H) or None (zeros), agent_mask (B, N) bool or None (all real), partners (B, N, k)
        or None (computed from positions with comm.dhc_partners_torch).
        """
        device = module_device(self)
        obs = as_float(obs, "obs", device)
        positions = as_long(positions, "positions", device)
        hidden = None if hidden is None else as_float(hidden, "hidden", device)
        if agent_mask is not None:
            agent_mask = torch.as_tensor(agent_mask, device=device).bool()
        batch, num_agents = check_batch_inputs(self.config, obs, positions, hidden, agent_mask)
        if hidden is None:
            hidden = obs.new_zeros(batch, num_agents, self.config.hidden_dim)
        if partners is None:
            partners = dhc_partners_torch(
                positions, self.config.obs_radius, self.config.max_partners, agent_mask)
        else:
            partners = as_long(partners, "partners", device)

        h = self.encode_batch(obs.flatten(0, 1), hidden.flatten(0, 1)).view(batch, num_agents, -1)
        receivers = (partners >= 0).any(-1)
        rows = receivers.nonzero(as_tuple=True)  # (b, i) of agents that communicate
        if rows[0].numel():
            own = rows[1][:, None]
            members = torch.cat([own, partners[rows]], dim=1)  # self first, then partners
            member_valid = members >= 0
            member_index = members.clamp(min=0)
            for _ in range(self.config.comm_rounds):
                member_h = h[rows[0][:, None], member_index]
                updated = self.round_batch(h[rows], member_h, member_valid)
                h = h.index_put(rows, updated)
        q = self.head(h)
        if agent_mask is not None:
            keep = agent_mask[..., None]
            q, h = q * keep, h * keep
        comm_mask = torch.zeros(batch, num_agents, num_agents + 1, dtype=torch.bool, device=device)
        # Column N collects the -1 (no partner) entries and is dropped.
        slot = torch.where(partners >= 0, partners, torch.full_like(partners, num_agents))
        comm_mask.scatter_(2, slot, True)
        return StepOutput(q=q, hidden=h, comm_mask=comm_mask[..., :num_agents], partners=partners)
