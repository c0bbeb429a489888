"""Structured map families (mazes, rooms, warehouse), their instances and the training mix."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.lib.stride_tricks import sliding_window_view

from mapf_fleet.grid.errors import InstanceError
from mapf_fleet.grid.instance import free_components
from mapf_fleet.grid.maps import (MAP_KINDS, TaskMix, capacity, generate_kind_instance,
                                  generate_map, maze_grid, place_agents, rooms_grid,
                                  sample_task_instance, warehouse_grid)
from mapf_fleet.training.config import TrainConfig, TrainConfigError, config_from_dict

STRUCTURED = ("maze", "rooms", "warehouse")


def free_square_sides(grid: np.ndarray, side: int) -> np.ndarray:
    """bool (H-side+1, W-side+1): the side x side square with this top-left corner is all free."""
    return (sliding_window_view(grid, (side, side)) == 0).all(axis=(-2, -1))


def covered_by_free_square(grid: np.ndarray, side: int) -> np.ndarray:
    """bool (H, W): the cell lies inside some free side x side square."""
    corners = free_square_sides(grid, side)
    covered = np.zeros(grid.shape, bool)
    for dr in range(side):
        for dc in range(side):
            covered[dr:dr + corners.shape[0], dc:dc + corners.shape[1]] |= corners
    return covered


def test_helpers_detect_width():
    grid = np.ones((6, 6), np.uint8)
    grid[1:3, 1:5] = 0  # a corridor two wide
    assert covered_by_free_square(grid, 2)[grid == 0].all()
    assert not free_square_sides(grid, 3).any()
    grid[3, 1] = 0  # a one-wide stub: not covered by a 2x2 square
    assert not covered_by_free_square(grid, 2)[grid == 0].all()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), size=st.integers(8, 45), width=st.sampled_from([1, 2]),
       loops=st.sampled_from([0.0, 0.1, 0.5, 1.0]))
def test_maze_corridors_have_the_stated_width(seed, size, width, loops):
    grid = maze_grid(size, seed, corridor_width=width, loop_fraction=loops)
    free = grid == 0
    # every free cell lies in a free w x w square, and no free (w+1) x (w+1) square exists
    assert covered_by_free_square(grid, width)[free].all()
    assert not free_square_sides(grid, width + 1).any()
    assert free_components(grid).max() == 1


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(STRUCTURED),
       height=st.integers(8, 50), width=st.integers(8, 50))
def test_structured_maps_are_one_connected_region(seed, kind, height, width):
    grid = generate_map(kind, (height, width), seed)
    assert grid.shape == (height, width) and grid.dtype == np.uint8
    labels = free_components(grid)
    assert labels.max() == 1, f"{kind} map has {labels.max()} free regions"
    # the minimal map of the drawn parameters (what capacity() counts) fits in every map
    if height == width:
        assert (grid == 0).sum() >= 2 * capacity(kind, height)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(MAP_KINDS), size=st.integers(8, 40),
       fill=st.floats(0.0, 1.0))
def test_generated_instances_validate_and_repeat_per_seed(seed, kind, size, fill):
    agents = int(fill * capacity(kind, size))
    inst = generate_kind_instance(kind, size, agents, seed)
    inst.validate()
    assert inst.num_agents == agents and inst.size == (size, size)
    cells = np.concatenate([inst.starts, inst.goals])
    assert len({tuple(c) for c in cells.tolist()}) == 2 * agents  # all 2N cells distinct
    labels = free_components(inst.grid)
    if agents:  # every agent in one connected region
        assert len(np.unique(labels[cells[:, 0], cells[:, 1]])) == 1 or kind == "random"
        assert (labels[inst.starts[:, 0], inst.starts[:, 1]]
                == labels[inst.goals[:, 0], inst.goals[:, 1]]).all()
    assert generate_kind_instance(kind, size, agents, seed) == inst
    assert generate_kind_instance(kind, size, agents, np.random.default_rng(seed)) == inst


def test_seeds_differ():
    for kind in STRUCTURED:
        maps = {generate_map(kind, 30, seed).tobytes() for seed in range(6)}
        assert len(maps) > 1, kind


def test_rooms_and_warehouse_shapes():
    grid = rooms_grid(31, 0, room_size=4, extra_door_fraction=0.0)
    assert (grid[0] == 1).all() and (grid[:, -1] == 1).all()  # walled border
    # 6 x 6 rooms, a spanning tree of 35 one-cell doors: walls minus 35 cells are obstacles
    walls = np.zeros_like(grid)
    lines = np.linspace(0, 30, 7).round().astype(int)
    walls[lines, :] = 1
    walls[:, lines] = 1
    assert walls.sum() - grid.sum() == 35
    shelves = warehouse_grid(20, 0, shelf_depth=2, shelf_length=4, aisle_width=1,
                             cross_aisle_width=2)
    assert shelves.sum() == 5 * 3 * 8  # 5 block rows x 3 blocks of 2 x 4
    assert (shelves[:2] == 0).all() and (shelves[:, :2] == 0).all()  # free border


def test_bad_parameters_name_field_and_value():
    with pytest.raises(ValueError, match="corridor_width must be one of"):
        maze_grid(20, 0, corridor_width=3)
    with pytest.raises(ValueError, match="loop_fraction must be in"):
        maze_grid(20, 0, loop_fraction=1.5)
    with pytest.raises(ValueError, match="sides >= 8"):
        generate_map("rooms", 5, 0)
    with pytest.raises(ValueError, match="map kind must be one of"):
        generate_map("forest", 20, 0)
    with pytest.raises(ValueError, match="unknown parameter"):
        generate_kind_instance("random", 20, 2, 0, corridor_width=1)
    with pytest.raises(InstanceError, match="no room for 200 start/goal pairs"):
        generate_kind_instance("maze", 20, 200, 0)
    grid = np.ones((8, 8), np.uint8)
    grid[0, :3] = 0
    with pytest.raises(InstanceError, match="has 3 cells"):
        place_agents(grid, 2, 0)


MIX = {"kinds": {"random": 2, "maze": 1, "rooms": 1, "warehouse": 1},
       "sizes": [20, 40], "agents": [4, 16, 64]}


def test_sample_task_instance_follows_the_mix():
    mix = TaskMix.from_dict(MIX)
    rng = np.random.default_rng(5)
    draws = [sample_task_instance(mix, rng) for _ in range(300)]
    kinds = [d.kind for d in draws]
    assert set(kinds) == set(MAP_KINDS)
    assert 0.3 < kinds.count("random") / len(kinds) < 0.5  # weight 2 of 5
    for d in draws[:40]:
        d.instance.validate()
        assert d.size in (20, 40) and d.num_agents in (4, 16, 64)
        assert d.instance.size == (d.size, d.size) and d.instance.num_agents == d.num_agents
    again = [sample_task_instance(MIX, np.random.default_rng(5)) for _ in range(1)]
    assert again[0].instance == draws[0].instance and again[0].kind == draws[0].kind


@pytest.mark.parametrize("mix,words", [
    ({**MIX, "kinds": {"forest": 1}}, "unknown map kind 'forest'"),
    ({**MIX, "kinds": {"maze": -1}}, "weight of 'maze' = -1"),
    ({**MIX, "kinds": {"maze": 0}}, "must not all be 0"),
    ({**MIX, "sizes": [4]}, "sizes: entry 4 must be an integer >= 8"),
    ({**MIX, "agents": []}, "agents = []"),
    ({**MIX, "agents": [0]}, "agents: entry 0"),
    ({**MIX, "sizes": [10]}, "64 agents do not fit every random map of size 10"),
    ({"kinds": {"maze": 1}, "sizes": [20]}, "missing ['agents']"),
    ({**MIX, "seed": 1}, "unknown ['seed']"),
])
def test_bad_mix_in_train_config_names_field_and_value(mix, words):
    with pytest.raises(TrainConfigError) as err:
        config_from_dict({"task_mix": mix}, source="mix.yaml")
    assert "mix.yaml: field 'task_mix'" in str(err.value) and words in str(err.value)


def test_train_config_mix_default_and_valid():
    assert TrainConfig().task_mix == {}
    cfg = config_from_dict({"task_mix": MIX, "final_agents": 64})
    assert TaskMix.from_dict(cfg.task_mix).sizes == (20, 40)
    with pytest.raises(TrainConfigError, match="field 'task_mix' = 3"):
        config_from_dict({"task_mix": 3})
