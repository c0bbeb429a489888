"""The DCC learner's `comm_masks=` option: replayed decision-causal masks instead of recomputed."""

import numpy as np
import pytest
import torch

from mapf_fleet.models.synthetic import make_sensitive
from mapf_fleet.training.actor import EpisodeWorker, Task
from mapf_fleet.training.config import TrainConfig
from mapf_fleet.training.learner import Learner
from mapf_fleet.training.modelio import hidden_dim
from mapf_fleet.training.replay import PrioritizedSequenceReplay


def _setup(algo="dcc"):
    torch.manual_seed(0)
    cfg = TrainConfig(algo=algo, model_preset="small", num_actors=1, envs_per_actor=2,
                      max_episode_steps=12, seq_len=4, burn_in=2, n_step=2, gamma=0.9,
                      final_agents=6, final_map_size=10, obstacle_density=0.1, seed=0)
    learner = Learner(cfg, device="cpu")
    if algo == "dcc":
        make_sensitive(learner.model, 3)
        learner.sync_target()
    worker = EpisodeWorker(cfg, actor_index=0, seed=1)
    worker.set_weights(learner.cpu_weights(), 0)
    worker.set_task(Task(num_agents=6, map_size=10, alpha=0.0))
    sequences = worker.run(24)["sequences"]
    replay = PrioritizedSequenceReplay(len(sequences), cfg.window_len, cfg.seq_len, 6,
                                       hidden_dim(learner.model))
    for seq in sequences:
        replay.add(seq)
    return cfg, learner, replay.sample(len(sequences), beta=0.4)


def test_replayed_masks_of_the_same_weights_give_the_recomputed_loss():
    cfg, learner, batch = _setup()
    masks = learner.causal_masks(batch)
    assert masks.shape == batch.positions.shape[:3] + (6,)
    assert masks.any(), "the sensitive network should communicate somewhere"
    with torch.no_grad():
        q_re, target_re, mask_re = learner.q_and_targets(batch)
        q_rp, target_rp, mask_rp = learner.q_and_targets(batch, comm_masks=masks)
        loss_re = learner.compute_loss(batch)[0]
        loss_rp = learner.compute_loss(batch, comm_masks=masks)[0]
    torch.testing.assert_close(q_rp, q_re)
    torch.testing.assert_close(target_rp, target_re)
    assert torch.equal(mask_rp, mask_re)
    assert float(loss_rp) == pytest.approx(float(loss_re), rel=1e-6)
    # the replayed masks are really used: silencing everyone changes the Q-values
    with torch.no_grad():
        q_silent, _, _ = learner.q_and_targets(batch, comm_masks=np.zeros_like(masks))
    assert not torch.allclose(q_silent, q_re)
    # and an update runs with them
    priorities, stats = learner.update(batch, comm_masks=masks)
    assert np.isfinite(priorities).all() and stats["transitions"] > 0


def test_comm_masks_errors_name_the_argument():
    cfg, learner, batch = _setup()
    with pytest.raises(ValueError, match=r"comm_masks: expected shape \(B, W, N, N\)"):
        learner.update(batch, comm_masks=np.zeros((1, 2, 3, 3), bool))
    _, dhc, dhc_batch = _setup("dhc")
    with pytest.raises(ValueError, match="only the DCC learner"):
        dhc.compute_loss(dhc_batch, comm_masks=np.zeros(dhc_batch.positions.shape[:3] + (6,), bool))
    with pytest.raises(ValueError, match="only DCC"):
        dhc.causal_masks(dhc_batch)


def test_causal_check_skips_window_steps_outside_the_episode(monkeypatch):
    """Padding steps (positions FAR_AWAY) put every agent on one cell; the learner must not run
    the causal check on those pairs (their outputs are never used)."""
    from mapf_fleet.models.dcc import DCCNetwork
    from mapf_fleet.training.replay import FAR_AWAY

    cfg, learner, batch = _setup()
    pos = batch.positions
    real = pos[..., 0] != FAR_AWAY  # (B, W, N)
    assert (~real & batch.agent_mask[:, None, :]).any(), "the batch should have padding steps"
    cheb = np.abs(pos[:, :, :, None, :] - pos[:, :, None, :, :]).max(-1)
    pairs = (cheb <= 4) & real[..., :, None] & real[..., None, :]
    pairs &= batch.agent_mask[:, None, :, None] & batch.agent_mask[:, None, None, :]
    pairs &= ~np.eye(pos.shape[2], dtype=bool)
    expected_per_step = pairs.sum(axis=(0, 2, 3))  # (W,) variants per window step
    counted = []
    original = DCCNetwork.encode_with_variants

    def count(self, obs, last_action, hidden, owner, offsets):
        counted.append(len(owner))
        return original(self, obs, last_action, hidden, owner, offsets)

    monkeypatch.setattr(DCCNetwork, "encode_with_variants", count)
    learner.q_and_targets(batch)
    burn, length = cfg.burn_in, cfg.seq_len
    # target over the window, online burn-in, online trained steps
    steps = list(range(cfg.window_len)) + list(range(burn)) + list(range(burn, burn + length))
    assert counted == [int(expected_per_step[w]) for w in steps]
