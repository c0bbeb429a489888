"""Property tests over whole episodes, and the demo command."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.grid.env import EnvConfig, MAPFEnv
from mapf_fleet.grid.instance import generate_instance


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), size=st.integers(4, 16), agents=st.integers(1, 24),
       actions=st.lists(st.lists(st.integers(0, 4), min_size=24, max_size=24), min_size=1,
                        max_size=12))
def test_episode_never_shares_cells_or_swaps(seed, size, agents, actions):
    agents = min(agents, size * size // 4)
    inst = generate_instance(size, agents, 0.2, seed)
    env = MAPFEnv(inst, EnvConfig(max_steps=50))
    env.reset()
    for joint in actions:
        before = env.positions.copy()
        _, rewards, done, info = env.step(np.array(joint[:agents]))
        after = env.positions
        flat = after[:, 0] * size + after[:, 1]
        assert len(np.unique(flat)) == agents
        assert not inst.grid[after[:, 0], after[:, 1]].any()
        assert (np.abs(after - before).sum(axis=1) <= 1).all()
        swapped = (after[:, None, :] == before[None, :, :]).all(-1) \
            & (before[:, None, :] == after[None, :, :]).all(-1)
        np.fill_diagonal(swapped, False)
        assert not swapped.any()
        np.testing.assert_array_equal(rewards[info["collisions"]], -0.5)
        if done:
            break


def test_demo_prints_outcome(capsys):
    from mapf_fleet.grid.demo import main
    assert main(["--size", "12", "--agents", "3", "--seed", "2", "--max-steps", "40"]) == 0
    out = capsys.readouterr().out
    assert "success: " in out and "steps: " in out and "collisions: " in out


def test_grid_layer_imports_neither_torch_nor_rclpy():
    import os
    import subprocess
    import sys
    code = "import sys, mapf_fleet.grid; print('torch' in sys.modules or 'rclpy' in sys.modules)"
    # no ROS here, but any process the project starts stays on loopback
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=env)
    assert out.stdout.strip() == "False"
