"""Instances: validation errors, the seeded generator, the training density, DHC test sets."""

from pathlib import Path

import numpy as np
import pytest

from mapf_fleet.grid.errors import InstanceError, MapFormatError
from mapf_fleet.grid.heuristic import HeuristicCache, bfs_distances_many
from mapf_fleet.grid.instance import (Instance, generate_instance, load_dhc_testset,
                                      sample_training_density)

DHC_TESTSETS = Path("/work/shared/data/dhc_testsets")

GRID = np.array([[0, 0, 1, 0],
                 [0, 0, 1, 0],
                 [1, 1, 1, 0]], np.uint8)


@pytest.mark.parametrize("starts,goals,agent,cell,words", [
    ([(0, 0), (1, 1)], [(0, 1), (0, 2)], 1, (0, 2), "goal is on an obstacle"),
    ([(2, 0), (1, 1)], [(0, 1), (1, 0)], 0, (2, 0), "start is on an obstacle"),
    ([(0, 0), (1, 1)], [(0, 1), (3, 1)], 1, (3, 1), "goal is outside the 3x4 map"),
    ([(0, 0), (1, 1)], [(1, 0), (1, 0)], 0, (1, 0), "goal is shared with agent(s) [1]"),
    ([(0, 0), (0, 0)], [(1, 0), (0, 1)], 0, (0, 0), "start is shared"),
    ([(0, 0), (1, 1)], [(0, 1), (2, 3)], 1, (2, 3), "goal is unreachable from start (1, 1)"),
])
def test_invalid_instance_names_agent_and_cell(starts, goals, agent, cell, words):
    with pytest.raises(InstanceError) as err:
        Instance(GRID, np.array(starts), np.array(goals)).validate()
    assert err.value.agent == agent and err.value.cell == cell
    assert f"agent {agent}" in str(err.value) and f"(row={cell[0]}, col={cell[1]})" in str(err.value)
    assert words in str(err.value)


def test_valid_instance_and_start_on_other_goal():
    inst = Instance(GRID, np.array([(0, 0), (1, 1)]), np.array([(1, 1), (0, 0)])).validate()
    assert inst.num_agents == 2 and inst.size == (3, 4)
    assert inst.grid.dtype == np.uint8 and inst.starts.dtype == np.int64


def test_shape_errors():
    with pytest.raises(InstanceError, match="starts must have shape"):
        Instance(GRID, np.array([0, 0]).reshape(1, 2, 1), np.array([[0, 1]]))
    with pytest.raises(InstanceError, match="differ in number of agents"):
        Instance(GRID, np.array([[0, 0]]), np.array([[0, 1], [1, 1]]))
    with pytest.raises(InstanceError, match="only 0"):
        Instance(GRID * 2, np.array([[0, 0]]), np.array([[0, 1]]))


@pytest.mark.parametrize("seed", range(60))
def test_generated_instances_are_valid(seed):
    rng = np.random.default_rng(seed)
    size = int(rng.choice([10, 20, 40, 80]))
    agents = int(rng.integers(1, min(64, size * size // 10) + 1))
    density = float(rng.choice([0.0, 0.2, 0.3, sample_training_density(rng)]))
    inst = generate_instance(size, agents, density, rng)
    inst.validate()
    assert inst.size == (size, size) and inst.num_agents == agents
    cells = np.concatenate([inst.starts, inst.goals])
    flat = cells[:, 0] * size + cells[:, 1]
    assert len(np.unique(flat)) == 2 * agents             # all starts and goals distinct
    assert not inst.grid[cells[:, 0], cells[:, 1]].any()  # all free
    dist = bfs_distances_many(inst.grid, inst.goals)
    assert (dist[np.arange(agents), inst.starts[:, 0], inst.starts[:, 1]] > 0).all()


def test_generator_is_reproducible():
    a = generate_instance(40, 16, 0.3, 123)
    b = generate_instance(40, 16, 0.3, np.random.default_rng(123))
    c = generate_instance(40, 16, 0.3, 124)
    assert a == b and a != c


def test_generator_density_and_errors():
    grids = [generate_instance(40, 4, 0.3, s).grid for s in range(20)]
    assert abs(np.mean(grids) - 0.3) < 0.02
    with pytest.raises(ValueError, match="density"):
        generate_instance(10, 2, 1.0, 0)
    with pytest.raises(ValueError, match="cannot hold"):
        generate_instance(3, 5, 0.0, 0)


def test_training_density_is_triangular():
    rng = np.random.default_rng(0)
    samples = np.array([sample_training_density(rng) for _ in range(20000)])
    assert samples.min() >= 0.0 and samples.max() <= 0.5
    assert abs(samples.mean() - (0 + 0.33 + 0.5) / 3) < 0.005
    hist, edges = np.histogram(samples, bins=10, range=(0, 0.5))
    assert edges[np.argmax(hist)] == pytest.approx(0.3)   # mode bin holds 0.33


def test_heuristic_cache_reuses_entries():
    inst = generate_instance(20, 8, 0.3, 1)
    cache = HeuristicCache(max_maps=2)
    first = cache.bits(inst.grid, inst.goals)
    assert cache.misses == 8 and cache.hits == 0
    again = cache.bits(inst.grid.copy(), inst.goals[::-1])
    assert cache.hits == 8 and np.array_equal(again, first[::-1])
    for s in (2, 3):
        other = generate_instance(20, 2, 0.3, s)
        cache.bits(other.grid, other.goals)
    cache.bits(inst.grid, inst.goals[:1])   # evicted (LRU of 2 maps): computed again
    assert cache.misses == 8 + 4 + 1


@pytest.mark.skipif(not DHC_TESTSETS.exists(), reason="shared DHC test sets absent")
@pytest.mark.parametrize("agents", [4, 64])
def test_load_dhc_testset(agents):
    path = DHC_TESTSETS / f"40length_{agents}agents.npz"
    if not path.exists():
        pytest.skip(f"{path} absent")
    instances = load_dhc_testset(path)
    assert len(instances) == 200
    assert all(i.size == (40, 40) and i.num_agents == agents for i in instances)
    raw = np.load(path)
    np.testing.assert_array_equal(instances[7].starts, raw["starts"][7])
    np.testing.assert_array_equal(instances[7].grid, raw["maps"][7])


def test_load_dhc_testset_bad_files(tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(path, maps=np.zeros((2, 5, 5), np.uint8), starts=np.zeros((2, 1, 2), np.int16))
    with pytest.raises(MapFormatError, match=r"bad\.npz: missing array\(s\) \['goals'\]"):
        load_dhc_testset(path)
    maps = np.zeros((2, 5, 5), np.uint8); maps[1, 4, 4] = 1
    starts = np.zeros((2, 1, 2), np.int16)
    goals = np.full((2, 1, 2), 4, np.int16)
    np.savez(path, maps=maps, starts=starts, goals=goals)
    with pytest.raises(MapFormatError, match=r"instance 1: agent 0, cell \(row=4, col=4\)"):
        load_dhc_testset(path)
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(MapFormatError, match="junk.npz"):
        load_dhc_testset(tmp_path / "junk.npz")
