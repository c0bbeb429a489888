"""Prioritized sequence replay: sum tree, proportional sampling, importance weights, n-step."""

import numpy as np
import pytest

from mapf_fleet.training.episodes import EpisodeRecord, episode_to_sequences, n_step_components
from mapf_fleet.training.replay import (PrioritizedSequenceReplay, SumTree, pack_obs,
                                        unpack_obs)


def test_sum_tree_totals_and_find():
    tree = SumTree(5)
    tree.update(np.arange(5), np.array([1.0, 2.0, 3.0, 4.0, 0.0]))
    assert tree.total == pytest.approx(10.0)
    # cumulative intervals: [0,1) -> 0, [1,3) -> 1, [3,6) -> 2, [6,10) -> 3
    assert tree.find(np.array([0.5, 1.0, 2.99, 3.0, 9.99])).tolist() == [0, 1, 1, 2, 3]
    tree.update(np.array([1, 1]), np.array([5.0, 0.5]))  # duplicate index: last write wins
    assert tree.total == pytest.approx(8.5)


def test_sum_tree_rejects_negative():
    with pytest.raises(ValueError):
        SumTree(4).update(np.array([0]), np.array([-1.0]))


def _sequence(num_agents=2, window=5, seq_len=3, hidden=4, reward=0.0):
    return {
        "obs_bits": np.zeros((window, num_agents, 61), np.uint8),
        "positions": np.zeros((window, num_agents, 2), np.int16),
        "last_actions": np.full((window, num_agents), -1, np.int8),
        "actions": np.zeros((seq_len, num_agents), np.uint8),
        "returns": np.full((seq_len, num_agents), reward, np.float32),
        "boot_discount": np.ones(seq_len, np.float32),
        "boot_index": np.arange(seq_len, dtype=np.int16) + 2,
        "step_mask": np.ones(seq_len, bool),
        "start_index": 0,
        "hidden": np.zeros((num_agents, hidden), np.float16),
    }


def _replay(capacity=8):
    return PrioritizedSequenceReplay(capacity, window_len=5, seq_len=3, max_agents=3,
                                     hidden_dim=4, alpha=0.6, seed=1)


def test_sampling_follows_priorities_and_weights():
    replay = _replay()
    for _ in range(4):
        replay.add(_sequence())
    replay.update_priorities(np.arange(4), np.array([1.0, 2.0, 4.0, 8.0]))
    p = (np.array([1.0, 2.0, 4.0, 8.0]) + replay.eps) ** 0.6
    expected = p / p.sum()
    np.testing.assert_allclose(replay.probabilities(np.arange(4)), expected, rtol=1e-9)
    counts = np.bincount(np.concatenate([replay.sample_indices(64) for _ in range(300)]),
                         minlength=4)
    np.testing.assert_allclose(counts / counts.sum(), expected, atol=0.02)
    w = replay.importance_weights(np.arange(4), beta=0.4)
    raw = (4 * expected) ** -0.4
    np.testing.assert_allclose(w, raw / raw.max(), rtol=1e-5)
    assert w[0] == pytest.approx(1.0) and w[3] < w[2] < w[1] < w[0]


def test_new_items_get_max_priority_and_ring_overwrites():
    replay = _replay(capacity=3)
    replay.add(_sequence())
    replay.update_priorities(np.array([0]), np.array([5.0]))
    slot = replay.add(_sequence(num_agents=3, reward=7.0))
    assert replay.tree.get(np.array([slot]))[0] == pytest.approx((5.0 + replay.eps) ** 0.6)
    replay.add(_sequence())
    replay.add(_sequence(num_agents=1, reward=3.0))  # overwrites slot 0
    assert len(replay) == 3 and replay.next_slot == 1
    assert replay.agent_mask[0].tolist() == [True, False, False]
    assert replay.returns[0, 0].tolist() == [3.0, 0.0, 0.0]
    batch = replay.sample(4, beta=0.4)
    assert batch.obs.shape == (4, 5, 3, 6, 9, 9) and batch.hidden.shape == (4, 3, 4)


def test_replay_rejects_too_many_agents():
    with pytest.raises(ValueError, match="agents"):
        _replay().add(_sequence(num_agents=4))


def test_obs_pack_roundtrip():
    obs = (np.random.default_rng(0).random((3, 2, 6, 9, 9)) > 0.5).astype(np.float32)
    np.testing.assert_array_equal(unpack_obs(pack_obs(obs)), obs)


def test_n_step_targets_hand_made_episode():
    # 4 steps, rewards r0..r3, gamma 0.5, n = 2.
    rewards = np.array([1.0, 2.0, 4.0, 8.0])
    ret, disc, off = n_step_components(rewards, terminal=True, gamma=0.5, n=2)
    np.testing.assert_allclose(ret, [1 + 0.5 * 2, 2 + 0.5 * 4, 4 + 0.5 * 8, 8])
    assert off.tolist() == [2, 2, 2, 1]
    # bootstrap from o_{t+2}; the two last steps reach the terminal end: no bootstrap.
    np.testing.assert_allclose(disc, [0.25, 0.25, 0.0, 0.0])
    ret, disc, off = n_step_components(rewards, terminal=False, gamma=0.5, n=2)
    np.testing.assert_allclose(disc, [0.25, 0.25, 0.25, 0.5])  # time limit: bootstrap o_T
    # full target with a made-up value function V(o_k) = 10 k
    values = 10.0 * np.arange(5)
    target = ret + disc * values[np.arange(4) + off]
    np.testing.assert_allclose(target, [2 + 0.25 * 20, 4 + 0.25 * 30, 8 + 0.25 * 40, 8 + 0.5 * 40])


def test_episode_to_sequences_windows_and_bootstrap_indices():
    length, agents, hidden = 5, 2, 3
    obs = np.zeros((length + 1, agents, 6, 9, 9), np.float32)
    for t in range(length + 1):
        obs[t, :, 0, 0, 0] = t % 2  # tag observations to check the window alignment
    positions = np.arange(length + 1)[:, None, None].repeat(agents, 1).repeat(2, 2)
    ep = EpisodeRecord(obs=obs, positions=positions,
                       actions=np.tile(np.arange(length)[:, None] % 5, (1, agents)),
                       rewards=np.ones((length, agents), np.float32),
                       hidden=np.arange(length + 1)[:, None, None] * np.ones((1, agents, hidden)),
                       terminal=True)
    seqs = episode_to_sequences(ep, seq_len=3, burn_in=2, n_step=2, gamma=0.9)
    assert len(seqs) == 2
    first, second = seqs
    # sequence 0: window index 0 is episode step -2 (padding); real data starts at index 2
    assert first["start_index"] == 2 and first["hidden"][0, 0] == 0
    assert first["positions"][2:, 0, 0].tolist() == [0, 1, 2, 3, 4]
    assert first["boot_index"].tolist() == [4, 5, 6]
    # sequence 1: steps 3, 4 (third is padding); window starts at step 1 with hidden of step 1
    assert second["start_index"] == 0 and second["hidden"][0, 0] == 1
    assert second["step_mask"].tolist() == [True, True, False]
    assert second["positions"][:, 0, 0].tolist() == [1, 2, 3, 4, 5, -10000, -10000]
    assert second["boot_index"][:2].tolist() == [4, 4]  # both bootstrap at o_5 = end (index 4)
    np.testing.assert_allclose(second["boot_discount"][:2], [0.0, 0.0])  # terminal
    np.testing.assert_allclose(second["returns"][:2, 0], [1.9, 1.0])
    assert second["last_actions"][:5, 0].tolist() == [0, 1, 2, 3, 4]
    assert first["last_actions"][:4, 0].tolist() == [-1, -1, -1, 0]  # padding, none, a_0


def test_replay_survives_a_save_and_reload(tmp_path):
    """RUN/replay.npz round trip: the same sequences, priorities and counters, so a resumed run
    samples what the stopped one would have (partly filled and wrapped-around buffers)."""
    from mapf_fleet.training import run_state

    for count in (3, 7):  # capacity 5: partly filled, then wrapped (next_slot 2)
        replay = _replay(capacity=5)
        for k in range(count):
            replay.add(_sequence(num_agents=1 + k % 3, reward=float(k)))
        replay.update_priorities(np.arange(len(replay)), np.arange(len(replay)) + 1.0)
        run_state.save_replay(tmp_path, replay.state_dict())
        restored = _replay(capacity=5)
        restored.load_state_dict(run_state.load_replay(tmp_path))
        assert (len(restored), restored.next_slot, restored.added_steps) == \
            (len(replay), replay.next_slot, replay.added_steps)
        assert restored.max_priority == replay.max_priority
        np.testing.assert_allclose(restored.probabilities(np.arange(len(replay))),
                                   replay.probabilities(np.arange(len(replay))))
        a, b = replay.sample(6, beta=0.4), restored.sample(6, beta=0.4)  # same rng seed
        for name in ("indices", "returns", "agent_mask", "actions", "weights"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert replay.returns[:len(replay), 0, 0].tolist() == restored.returns[:len(replay), 0, 0].tolist()


def test_replay_of_another_shape_is_refused_by_name(tmp_path):
    from mapf_fleet.training import run_state

    replay = _replay(capacity=5)
    replay.add(_sequence())
    state = replay.state_dict()
    other = PrioritizedSequenceReplay(5, window_len=5, seq_len=3, max_agents=3, hidden_dim=8)
    with pytest.raises(ValueError, match="replay hidden_dim: saved 4, this run uses 8"):
        other.load_state_dict(state)
    assert len(other) == 0
    (tmp_path / run_state.REPLAY_FILE).write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="replay.npz: not a readable replay file"):
        run_state.load_replay(tmp_path)
    assert run_state.load_replay(tmp_path / "empty") is None
