"""DCC network (Ma, Luo and Pan 2021) as in the paper's appendix and the reference code.

One step of agent i:
  h_i  = GRU([encoder(obs_i), onehot(last_action_i)], hidden_i)          (encode)
  Decision-causal selection: a_i = argmax dueling(h_i); for every FOV neighbour j, a_i,-j is the
  same computed from obs_i with j's cell erased in channel 0 (same hidden_i and last action).
  i requests from j when a_i,-j != a_i.                           (encode_with_variants)
  Request layer, at each receiver j with at least one requester:
    h1_j = GRU_req(attention(query LN(h_j), messages from [j itself] + requesters i), h_j)
    and h1_j = h_j for agents without requesters.                          (request_comm)
  Reply layer, at each requester i: the same with the transposed mask and the request-layer
    outputs: h2_i = GRU_rep(attention(query LN(h1_i), [i itself] + repliers j), h1_i),
    h2_i = h1_i for agents that requested nothing.                          (reply_comm)
  q_i = dueling(h2_i).
A message from sender s to receiver r is key/value of [LN(h_s), embed(onehot(pos_s - pos_r))]
(relative position one-hot over the (2r+1)^2 FOV, comm.relative_position_index). The "itself"
message (offset (0, 0)) is there when config.attend_self (this project's default); the DCC
reference attends over the senders only (attend_self=False).

Carried hidden: h2_i, the reply-layer output (the final, post-communication hidden), as the
reference's step and training forward both do. The pre-communication h_i is not carried.

`step` is the batched step (evaluator, trainer); the fleet's exchange (`models.exchange`) runs
the same pieces (`encode_with_variants`, `greedy_actions`, `receive` with `request_comm` /
`reply_comm`, `head`) for the robots of one process, with the messages they received.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from mapf_fleet.grid.actions import NUM_ACTIONS

from .comm import fov_neighbour_table, relative_position_index
from .common import (DuelingHead, StepOutput, as_float, as_long, check_batch_inputs,
                     module_device, pad_rows, padded_rows)
from .config import ModelConfig


class DCCCommLayer(nn.Module):
    """One request or reply layer; attribute names follow the reference's CommLayer."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        hidden, width = config.hidden_dim, config.num_heads * config.head_dim
        self.num_heads, self.head_dim = config.num_heads, config.head_dim
        self.norm = nn.LayerNorm(hidden)
        self.position_embeddings = nn.Linear(config.fov**2, config.pos_embed_dim)
        self.message_key = nn.Linear(hidden + config.pos_embed_dim, width)
        self.message_value = nn.Linear(hidden + config.pos_embed_dim, width)
        self.hidden_query = nn.Linear(hidden, width)
        self.head_agg = nn.Linear(width, width)
        self.update = nn.GRUCell(width, hidden)

    def embed_positions(self, position_index: torch.Tensor) -> torch.Tensor:
        # Linear(one_hot(index)) is exactly this column gather plus bias.
        return self.position_embeddings.weight.t()[position_index] + self.position_embeddings.bias

    def forward(self, own_h: torch.Tensor, sender_h: torch.Tensor,
                position_index: torch.Tensor, sender_valid: torch.Tensor) -> torch.Tensor:
        """own_h (M, H), sender_h (M, S, H), position_index (M, S), sender_valid (M, S).

        Returns the GRU-updated (M, H); the caller passes only receivers (rows with at least
        one real sender).
        """
        m, s, _ = sender_h.shape
        query = self.hidden_query(self.norm(own_h)).view(m, 1, self.num_heads, self.head_dim)
        message = torch.cat([self.norm(sender_h), self.embed_positions(position_index)], dim=-1)
        key = self.message_key(message).view(m, s, self.num_heads, self.head_dim)
        value = self.message_value(message).view(m, s, self.num_heads, self.head_dim)
        scores = (query * key).sum(-1) / math.sqrt(self.head_dim)  # (M, S, heads)
        scores = scores.masked_fill(~sender_valid[:, :, None], float("-inf"))
        weights = torch.softmax(scores, dim=1)  # over senders
        aggregated = self.head_agg((weights[..., None] * value).sum(1).reshape(m, -1))
        return self.update(aggregated, own_h)


class DCCNetwork(nn.Module):
    algo = "dcc"

    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        config = config if config is not None else ModelConfig.preset("dcc", "paper")
        if config.algo != "dcc":
            raise ValueError(f"DCCNetwork: config.algo must be 'dcc', got {config.algo!r}")
        self.config = config
        layers: list[nn.Module] = []
        in_channels = config.obs_shape[0]  # 6 channels, 7 with cost_to_go
        for out_channels in config.conv_channels:
            layers += [nn.Conv2d(in_channels, out_channels, 3, 1), nn.LeakyReLU(0.2, True)]
            in_channels = out_channels
        layers.append(nn.Flatten())
        self.obs_encoder = nn.Sequential(*layers)
        side = config.fov - 2 * len(config.conv_channels)
        self.latent_dim = in_channels * side * side + NUM_ACTIONS
        # Channels-last weights and inputs: oneDNN's CPU convolutions are faster in that layout
        # (docs/results.md, "Performance (2-core machine, no GPU)"); load_state_dict keeps it.
        self.obs_encoder.to(memory_format=torch.channels_last)
        self.recurrent = nn.GRUCell(self.latent_dim, config.hidden_dim)
        self.request_comm = DCCCommLayer(config)
        self.reply_comm = DCCCommLayer(config)
        self.head = DuelingHead(config.hidden_dim)

    @property
    def hidden_dim(self) -> int:
        return self.config.hidden_dim

    # ---- shared pieces ------------------------------------------------------------------

    def encode_batch(self, obs: torch.Tensor, last_action: torch.Tensor,
                hidden: torch.Tensor) -> torch.Tensor:
        """obs (M, C, fov, fov) (C = config.obs_shape[0]), last_action (M,) long in -1..4 (-1:
        none), hidden (M, H)."""
        rows = len(obs)
        if not torch.is_grad_enabled():
            obs, last_action, hidden = pad_rows(padded_rows(rows), obs, last_action, hidden)
        one_hot = F.one_hot(last_action.clamp(min=0), NUM_ACTIONS).to(obs.dtype)
        one_hot = one_hot * (last_action >= 0)[:, None].to(obs.dtype)
        features = self.obs_encoder(obs.contiguous(memory_format=torch.channels_last))
        latent = torch.cat([features, one_hot], dim=1)
        return self.recurrent(latent, hidden)[:rows]

    def greedy_actions(self, h: torch.Tensor) -> torch.Tensor:
        return self.head(h).argmax(-1)

    def _erased_variants(self, obs: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """Copies of obs (E, C, fov, fov), channel 0 cleared at offsets (E, 2) from the centre."""
        variants = obs.clone()
        cell = offsets + self.config.obs_radius
        variants[torch.arange(len(variants), device=obs.device), 0, cell[:, 0], cell[:, 1]] = 0.0
        return variants

    def encode_with_variants(self, obs, last_action, hidden, owner, offsets):
        """Encode every agent (M rows) and its erased variants (E rows, owner[e] in 0..M-1).

        Returns (h (M, H), greedy action of each variant (E,)). The variants never need
        gradients (they only decide who talks); without autograd everything runs as one
        encoder batch, which is the fast inference path.
        """
        variants = self._erased_variants(obs[owner], offsets)
        if torch.is_grad_enabled():
            h = self.encode_batch(obs, last_action, hidden)
            with torch.no_grad():
                variant_h = self.encode_batch(variants, last_action[owner], hidden[owner])
        else:
            both = self.encode_batch(torch.cat([obs, variants]),
                                torch.cat([last_action, last_action[owner]]),
                                torch.cat([hidden, hidden[owner]]))
            h, variant_h = both[: len(obs)], both[len(obs):]
        return h, self.greedy_actions(variant_h)

    # ---- batched ------------------------------------------------------------------------

    def step(self, obs, positions, hidden=None, last_action=None, agent_mask=None,
             comm_mask=None) -> StepOutput:
        """One step of B episodes x N agents (differentiable; wrap in torch.no_grad to act).

        obs (B, N, C, fov, fov) (C = config.obs_shape[0]), positions (B, N, 2) int, hidden
        (B, N, H) or None (zeros), last_action (B, N) int in -1..4 or None (-1 = no previous
        action: zero one-hot), agent_mask (B, N) bool or None, comm_mask (B, N, N) bool or None:
        a decision-causal mask recorded earlier ([b, i, j] = i requests from j); when given, the
        causal check is skipped (the trainer can replay the actor's masks, as the reference
        learner does).
        """
        cfg = self.config
        device = module_device(self)
        obs = as_float(obs, "obs", device)
        positions = as_long(positions, "positions", device)
        hidden = None if hidden is None else as_float(hidden, "hidden", device)
        if agent_mask is not None:
            agent_mask = torch.as_tensor(agent_mask, device=device).bool()
        batch, num_agents = check_batch_inputs(cfg, obs, positions, hidden, agent_mask)
        if hidden is None:
            hidden = obs.new_zeros(batch, num_agents, cfg.hidden_dim)
        if last_action is None:
            last_action = torch.full((batch, num_agents), -1, dtype=torch.long, device=device)
        last_action = as_long(last_action, "last_action", device)
        if tuple(last_action.shape) != (batch, num_agents):
            raise ValueError(f"last_action: expected {(batch, num_agents)}, "
                             f"got {tuple(last_action.shape)}")

        # Every agent's FOV neighbours (B, N, K), index order, -1 padded.
        table = fov_neighbour_table(positions, cfg.obs_radius, agent_mask)
        slot_valid = table >= 0
        table0 = table.clamp(min=0)
        batch_index = torch.arange(batch, device=device)[:, None, None]
        agent_index = torch.arange(num_agents, device=device)[:, None]
        # offsets[b, i, k] = pos of neighbour - pos of i  (sender - receiver when i receives)
        offsets = positions[batch_index, table0] - positions[:, :, None, :]
        offsets = offsets * slot_valid[..., None]  # empty slots: (0, 0), masked out later

        flat_obs, flat_hidden = obs.flatten(0, 1), hidden.flatten(0, 1)
        flat_last = last_action.flatten()
        if comm_mask is None:
            b_e, i_e, k_e = slot_valid.nonzero(as_tuple=True)
            owner = b_e * num_agents + i_e
            h_flat, variant_actions = self.encode_with_variants(
                flat_obs, flat_last, flat_hidden, owner, offsets[b_e, i_e, k_e])
            with torch.no_grad():
                own_actions = self.greedy_actions(h_flat)
            requests = torch.zeros_like(slot_valid)
            requests[b_e, i_e, k_e] = variant_actions != own_actions[owner]
            comm_mask = torch.zeros(batch, num_agents, num_agents + 1, dtype=torch.bool,
                                    device=device)
            comm_mask.scatter_(2, torch.where(requests, table, num_agents), True)
            comm_mask = comm_mask[..., :num_agents]
        else:
            comm_mask = torch.as_tensor(comm_mask, device=device).bool()
            if tuple(comm_mask.shape) != (batch, num_agents, num_agents):
                raise ValueError(f"comm_mask: expected {(batch, num_agents, num_agents)}, "
                                 f"got {tuple(comm_mask.shape)}")
            h_flat = self.encode_batch(flat_obs, flat_last, flat_hidden)
            requests = slot_valid & comm_mask[batch_index, agent_index, table0]
        h = h_flat.view(batch, num_agents, -1)

        # Request layer: receiver r hears from its neighbours n that request from r.
        incoming = slot_valid & comm_mask[batch_index, table0, agent_index]
        h1 = self._comm(self.request_comm, h, table0, offsets, incoming)
        # Reply layer (transposed mask): requester i hears from the neighbours it requested.
        h2 = self._comm(self.reply_comm, h1, table0, offsets, requests)
        q = self.head(h2)
        if agent_mask is not None:
            keep = agent_mask[..., None]
            q, h2 = q * keep, h2 * keep
        return StepOutput(q=q, hidden=h2, comm_mask=comm_mask)

    def _comm(self, layer: DCCCommLayer, h: torch.Tensor, table0: torch.Tensor,
              offsets: torch.Tensor, senders: torch.Tensor) -> torch.Tensor:
        """Run `layer` for every agent with at least one sender; others keep h."""
        rows = senders.any(-1).nonzero(as_tuple=True)
        if rows[0].numel() == 0:
            return h
        updated = self.receive(layer, h[rows], h[rows[0][:, None], table0[rows]], offsets[rows],
                               senders[rows])
        return h.index_put(rows, updated)

    def receive(self, layer: DCCCommLayer, own: torch.Tensor, sender_h: torch.Tensor,
                offsets: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """One comm layer at receivers with at least one sender: own (M, H), the senders'
        vectors (M, S, H) at `offsets` (M, S, 2) (sender - receiver), `valid` (M, S) -> the
        receivers' updated (M, H). The batched step and the fleet's exchange both call it."""
        position_index = relative_position_index(offsets, self.config.obs_radius)
        if self.config.attend_self:
            sender_h, position_index, valid = self.with_self(own, sender_h, position_index, valid)
        return layer(own, sender_h, position_index, valid)

    def with_self(self, own, sender_h, position_index, valid):
        """Prepend each receiver's own message at offset (0, 0) (the FOV centre)."""
        centre = self.config.obs_radius * (self.config.fov + 1)
        self_index = torch.full_like(position_index[:, :1], centre)
        self_valid = torch.ones_like(valid[:, :1])
        return (torch.cat([own[:, None], sender_h], 1), torch.cat([self_index, position_index], 1),
                torch.cat([self_valid, valid], 1))
