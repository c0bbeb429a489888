"""The trainer's only contact with `mapf_fleet.models`: build a network from a `TrainConfig` and
run one batched step with the right arguments for DHC or DCC."""

from __future__ import annotations

import torch

from .config import TrainConfig


def model_config(cfg: TrainConfig):
    from mapf_fleet.models.config import ModelConfig

    return ModelConfig.preset(cfg.algo, cfg.model_preset, **cfg.model_overrides)


def build_model(cfg: TrainConfig) -> torch.nn.Module:
    mcfg = model_config(cfg)
    if cfg.algo == "dhc":
        from mapf_fleet.models.dhc import DHCNetwork

        return DHCNetwork(mcfg)
    from mapf_fleet.models.dcc import DCCNetwork

    return DCCNetwork(mcfg)


def hidden_dim(model: torch.nn.Module) -> int:
    return int(model.config.hidden_dim)


def model_step(model, algo: str, obs, positions, hidden, last_actions, agent_mask=None,
               comm_mask=None):
    """One batched step; `last_actions` (B, N) with -1 = none (used by DCC only); `comm_mask`
    (B, N, N) bool replays a recorded DCC decision-causal mask (None: the network computes it)."""
    if algo == "dcc":
        return model.step(obs, positions, hidden=hidden, last_action=last_actions,
                          agent_mask=agent_mask, comm_mask=comm_mask)
    if comm_mask is not None:
        raise ValueError("comm_mask: only DCC replays recorded communication masks")
    return model.step(obs, positions, hidden=hidden, agent_mask=agent_mask)


