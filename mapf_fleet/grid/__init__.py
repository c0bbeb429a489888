"""Grid world of mapf_fleet (numpy only): maps, instances, MovingAI files, heuristic channels,
the DHC/DCC environment and the cooperative reward. See docs/architecture.md."""

from .actions import ACTION_DELTAS, DOWN, LEFT, NUM_ACTIONS, RIGHT, STAY, UP
from .batch_env import BatchMAPFEnv
from .env import EnvConfig, MAPFEnv, observe, resolve_moves, step_rewards
from .errors import InstanceError, MapFormatError
from .heuristic import (HeuristicCache, bfs_distances, bfs_distances_many, cached_heuristic_channels,
                        heuristic_channels)
from .instance import Instance, generate_instance, load_dhc_testset, sample_training_density
from .observation import ObservationBuilder
from .movingai import (ScenarioEntry, load_movingai_instances, read_map, read_scen, write_map,
                       write_scen)
from .policies import heuristic_policy
from .reward import CooperativeReward, fov_neighbours

__all__ = [
    "ACTION_DELTAS", "DOWN", "LEFT", "NUM_ACTIONS", "RIGHT", "STAY", "UP",
    "BatchMAPFEnv", "EnvConfig", "MAPFEnv", "observe", "resolve_moves", "step_rewards",
    "InstanceError", "MapFormatError",
    "HeuristicCache", "bfs_distances", "bfs_distances_many", "cached_heuristic_channels",
    "heuristic_channels",
    "Instance", "generate_instance", "load_dhc_testset", "sample_training_density",
    "ObservationBuilder",
    "ScenarioEntry", "load_movingai_instances", "read_map", "read_scen", "write_map", "write_scen",
    "heuristic_policy",
    "CooperativeReward", "fov_neighbours",
]
