"""FOV observations of DHC/DCC: the one builder every caller that runs a model uses (the
environment and the batched environment, hence the evaluator, the actors and DAgger; the
evaluator's lifelong rollout; the fleet's policy processes, for the robots they host).

The static part of every agent's observation (obstacle bit + its four heuristic bits) is packed
into one byte per cell and padded once per (map, goals); an observation then gathers one byte
per FOV cell for the static part and one for the agents, and unpacks the bits into the
(N, 6, 9, 9) float32 observation. Agents whose goals change (a lifelong run, a fleet process)
are observed by `grid.goal_observer.GoalObserver`, which keeps the padded maps per goal.

Observations (`OBSERVATIONS`, `EnvConfig.observation`, recorded in a model's config): "paper",
the six channels above, or "cost_to_go", the same plus a 7th channel, the agent's normalised
cost-to-go over its FOV (`cost_to_go_channel`), gathered from its padded BFS distance map.
"""

from __future__ import annotations

import numpy as np

from .heuristic import (UNREACHABLE, HeuristicCache, compact_distances, default_cache,
                        pack_heuristic_channels)

NUM_OBS_CHANNELS = 6  # the paper's observation
OBSERVATIONS = ("paper", "cost_to_go")
COST_TO_GO_CHANNEL = NUM_OBS_CHANNELS  # index of the cost-to-go channel, after the paper's six


def observation_channels(observation: str) -> int:
    """How many channels `observation` has (6 paper, 7 cost_to_go)."""
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation must be one of {OBSERVATIONS}, got {observation!r}")
    return NUM_OBS_CHANNELS + (observation == "cost_to_go")


def check_positions(positions, shape) -> np.ndarray:
    """int64 (N, 2) positions, each inside a map of `shape` (a clear error otherwise)."""
    positions = np.asarray(positions)
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise ValueError(f"positions must have shape (N, 2), got {positions.shape}")
    positions = positions.astype(np.int64, copy=False)
    h, w = shape
    outside = (positions[:, 0] < 0) | (positions[:, 0] >= h) | (positions[:, 1] < 0) \
        | (positions[:, 1] >= w)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(f"agent {i} position {tuple(positions[i].tolist())} is outside the "
                         f"{h}x{w} map")
    return positions


def cost_to_go_steps(window_distances, radius: int) -> np.ndarray:
    """int8 (..., S*S): each FOV cell's BFS distance to the agent's goal minus the distance at the
    agent's own cell (the middle of the window), clipped to +-(2r+1); obstacle, off-map and
    unreachable cells (`UNREACHABLE` in `window_distances` (..., S*S)), and every cell when the
    agent's own cell cannot reach its goal, hold 2r+1. `cost_to_go_channel` normalises them."""
    d = np.asarray(window_distances).astype(np.int32)
    bound = 2 * int(radius) + 1
    centre = d[..., d.shape[-1] // 2, None]
    blocked = (d == UNREACHABLE) | (centre == UNREACHABLE)
    return np.where(blocked, bound, np.clip(d - centre, -bound, bound)).astype(np.int8)


def cost_to_go_channel(steps, radius: int) -> np.ndarray:
    """float32 cost-to-go channel from `cost_to_go_steps`: steps / (2r+1), within [-1, 1].

    Relative to the agent's own cell, as SSIL's normalised cost-to-go (Veerapaneni et al.,
    ICRA 2025), so the values do not grow with the distance to the goal; 2r+1 bounds every cell
    whose difference the FOV's geometry allows (|steps| <= 2r) strictly inside (-1, 1), so the
    blocked value 1.0 (obstacles, off the map, unreachable) differs from every free cell except
    those 2r+1 or more steps farther from the goal than the agent (behind a wall), which clip
    to it. Every value is a multiple of 1/(2r+1): `steps_from_cost_to_go` inverts this exactly
    (int8 storage)."""
    return np.asarray(steps, dtype=np.float32) / np.float32(2 * int(radius) + 1)


def steps_from_cost_to_go(channel, radius: int) -> np.ndarray:
    """int8 steps of a cost-to-go channel (the inverse of `cost_to_go_channel`)."""
    return np.rint(np.asarray(channel, dtype=np.float32) * (2 * int(radius) + 1)).astype(np.int8)


def pad_distances(distances: np.ndarray, radius: int) -> np.ndarray:
    """(N, H+2r, W+2r) BFS distance maps (N, H, W) with `UNREACHABLE` off the map (its compact
    integer type: one map per agent)."""
    distances = compact_distances(distances)
    n, h, w = distances.shape
    r = int(radius)
    padded = np.full((n, h + 2 * r, w + 2 * r), UNREACHABLE, dtype=distances.dtype)
    padded[:, r:r + h, r:r + w] = distances
    return padded


class ObservationBuilder:
    """Gathers agents' FOV windows from maps padded once per (map, goals).

    static byte per (agent, cell): bit 0 obstacle (off-map padded as obstacle), bits 1..4 the
    heuristic channels up/down/left/right (padded 0). `grids` is (B, H, W) (or (H, W)) and
    `map_of_agent` (N,) says on which map each agent is (B = 1 and all zeros for a single
    episode). With `distances` (N, H, W), each agent's BFS distances to its goal, observations
    get the cost-to-go channel (`cost_to_go_channel`).

    Two ways to use it: an environment keeps the agents' occupancy (`set_agents`,
    `move_agents`) and calls `build(positions)` each step; a caller holding only positions
    calls `observe(positions, agents)` (one map), e.g. a fleet process for the robots it hosts
    (built with `for_goals` on those robots' goals).
    """

    def __init__(self, grids: np.ndarray, heuristic_bits: np.ndarray, radius: int,
                 map_of_agent: np.ndarray | None = None, distances: np.ndarray | None = None):
        grids = np.asarray(grids)
        if grids.ndim == 2:
            grids = grids[None]
        b, h, w = grids.shape
        n = heuristic_bits.shape[0]
        map_of_agent = np.zeros(n, np.int64) if map_of_agent is None else map_of_agent
        r = int(radius)
        self.radius = r
        self.size = 2 * r + 1
        self.num_agents = n
        self.num_maps = b
        hp, wp = h + 2 * r, w + 2 * r
        static = np.ones((n, hp, wp), dtype=np.uint8)  # off-map: obstacle bit only
        static[:, r:r + h, r:r + w] = (grids[map_of_agent] != 0).astype(np.uint8) \
            | (heuristic_bits << 1)
        self.static = static.reshape(-1)
        self.distances = None if distances is None else pad_distances(distances, r).reshape(-1)
        self.channels = NUM_OBS_CHANNELS + (distances is not None)
        self.occupancy = np.zeros(b * hp * wp, dtype=np.uint8)
        offsets = np.arange(self.size)
        # flat offsets of a window relative to its top-left corner in the padded map
        self.window = (offsets[:, None] * wp + offsets[None, :]).reshape(-1)
        self.agent_base = np.arange(n, dtype=np.int64) * (hp * wp)
        self.map_base = map_of_agent * (hp * wp)
        self.wp = wp
        # padded flat index of an agent's own cell relative to its window corner
        self.centre = r * wp + r
        self.key = None  # for_goals: what it was built for (map, goals, observation)

    @classmethod
    def for_goals(cls, grid, goals, radius: int = 4, observation: str = "paper",
                  cache: HeuristicCache | None = None, guidance=None) -> "ObservationBuilder":
        """The builder of agents heading to `goals` (N, 2) on one map, for `observation`, with
        the heuristic bits (and distances) from `cache` (the process-wide one by default), under
        `guidance` (a `grid.guidance.Guidance`; None: BFS steps)."""
        cache = default_cache if cache is None else cache
        channels = observation_channels(observation)
        distances = cache.distances(grid, goals, guidance) if channels > NUM_OBS_CHANNELS \
            else None
        bits = cache.bits(grid, goals, guidance)  # found by the distances' search
        builder = cls(np.asarray(grid), bits, radius, distances=distances)
        builder.key = (np.asarray(grid).shape, np.asarray(grid).tobytes(),
                       np.asarray(goals).tobytes(), observation)
        return builder

    def corners(self, positions: np.ndarray) -> np.ndarray:
        # window top-left in padded coordinates == agent cell in map coordinates
        return positions[:, 0] * self.wp + positions[:, 1]

    def set_agents(self, positions: np.ndarray) -> None:
        self.occupancy[:] = 0
        self.occupancy[self.map_base + self.corners(positions) + self.centre] = 1

    def move_agents(self, old_positions: np.ndarray, new_positions: np.ndarray) -> None:
        self.occupancy[self.map_base + self.corners(old_positions) + self.centre] = 0
        self.occupancy[self.map_base + self.corners(new_positions) + self.centre] = 1

    def build(self, positions: np.ndarray) -> np.ndarray:
        """float32 (N, C, S, S) of every agent at `positions`, with the occupancy kept by
        `set_agents` / `move_agents`."""
        return self._gather(self.occupancy, positions, self.map_base)

    def observe(self, positions, agents=None) -> np.ndarray:
        """float32 (M, C, S, S) of agents `agents` (M,) (this builder's agents, in its order;
        None: all N), given every agent's `positions` (N, 2) on the one map: the agents not
        among `agents` are seen in channel 0 too."""
        if self.num_maps != 1:
            raise ValueError(f"ObservationBuilder.observe takes one map, this builder has "
                             f"{self.num_maps}: use set_agents and build")
        positions = np.asarray(positions, dtype=np.int64)
        own = positions if agents is None else positions[np.asarray(agents, dtype=np.int64)]
        if len(own) != self.num_agents:
            raise ValueError(f"observe: {len(own)} agents for a builder of {self.num_agents} "
                             f"(its goals)")
        occupancy = np.zeros_like(self.occupancy)
        occupancy[self.corners(positions) + self.centre] = 1
        return self._gather(occupancy, own, 0)

    def _gather(self, occupancy: np.ndarray, positions: np.ndarray, map_base) -> np.ndarray:
        corners = self.corners(positions)
        own_windows = (corners + self.agent_base)[:, None] + self.window  # (N, S*S)
        return assemble(occupancy[(corners + map_base)[:, None] + self.window],
                         self.static[own_windows],
                         None if self.distances is None else self.distances[own_windows],
                         self.channels, self.radius)


def assemble(agents, static, distances, channels: int, radius: int) -> np.ndarray:
    """float32 (N, C, S, S) from each agent's gathered window (N, S*S): the agents' occupancy,
    the static bytes (obstacle bit, then the heuristic bits) and the padded distances (None
    without the cost-to-go channel)."""
    n, cells = agents.shape
    s = 2 * radius + 1
    obs = np.empty((n, channels, cells), dtype=np.float32)
    obs[:, 0] = agents
    obs[:, 0, cells // 2] = 0.0  # the agent itself is not in its agent channel
    for bit in range(5):
        obs[:, 1 + bit] = (static >> bit) & 1
    if distances is not None:
        obs[:, COST_TO_GO_CHANNEL] = cost_to_go_channel(cost_to_go_steps(distances, radius),
                                                        radius)
    return obs.reshape(n, channels, s, s)


def observe(grid, positions, goals, channels, radius: int = 4, distances=None) -> np.ndarray:
    """float32 (N, 6, 2r+1, 2r+1) observations centred on each agent, (N, 7, ...) with
    `distances`.

    Channels: 0 other agents (self excluded), 1 obstacles (off-map cells count as obstacles),
    2..5 the agent's heuristic channels up/down/left/right (0 off the map). `channels` is the
    (N, 4, H, W) stack of the agents' heuristic channels; `goals` (N, 2) is only checked for
    shape, since the heuristic channels already encode the goals. `distances` (N, H, W), each
    agent's BFS distances to its goal (`HeuristicCache.distances`), adds channel 6, the
    "cost_to_go" observation's normalised cost-to-go (`cost_to_go_channel`).
    """
    grid = np.asarray(grid)
    positions = check_positions(positions, grid.shape)
    n = positions.shape[0]
    if np.asarray(goals).shape != (n, 2):
        raise ValueError(f"goals must have shape ({n}, 2), got {np.asarray(goals).shape}")
    channels = np.asarray(channels)
    if channels.shape != (n, 4, *grid.shape):
        raise ValueError(f"channels must have shape ({n}, 4, {grid.shape[0]}, {grid.shape[1]}), "
                         f"got {channels.shape}")
    if distances is not None and np.asarray(distances).shape != (n, *grid.shape):
        raise ValueError(f"distances must have shape ({n}, {grid.shape[0]}, {grid.shape[1]}), "
                         f"got {np.asarray(distances).shape}")
    builder = ObservationBuilder(grid, pack_heuristic_channels(channels), radius,
                                  distances=distances)
    builder.set_agents(positions)
    return builder.build(positions)
