"""FOV observations of DHC/DCC: the one builder every caller that runs a model uses (the
environment and the batched environment, hence the evaluator, the actors and DAgger; the
evaluator's lifelong rollout; the fleet's policy processes, for the robots they host).

The static part of every agent's observation (obstacle bit + its four heuristic bits) is packed
into one byte per cell and padded once per (map, goals); an observation then gathers one byte
per FOV cell for the static part and one for the agents, and unpacks the bits into the
(N, 6, 9, 9) float32 observation.

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
        return _assemble(occupancy[(corners + map_base)[:, None] + self.window],
                         self.static[own_windows],
                         None if self.distances is None else self.distances[own_windows],
                         self.channels, self.radius)


def _assemble(agents, static, distances, channels: int, radius: int) -> np.ndarray:
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


# A batch of new goals whose whole searches would write at least this many bytes (distance
# rows, heuristic bits and the observer's padded maps) is first searched only around its agents
# (`GoalObserver`'s windows): a fleet's first tick at 10,000 agents on a 512x512 map would
# otherwise write about 10 GB before the first decision (docs/results.md, "The first tick at
# 10,000 agents").
WINDOW_FROM_BYTES = 1 << 30
# How far (cells) an agent may move from where its goal's window was searched before the
# window no longer holds its field of view; the windows are searched whole within this many
# observations (a robot moves at most one cell a tick).
WINDOW_MARGIN = 8


class GoalObserver:
    """FOV observations of agents on one map whose goals change (a lifelong run, a fleet process):
    `observe(positions, goals, agents)` equals `ObservationBuilder.for_goals(grid, goals, radius,
    observation).observe(positions, agents)` without rebuilding anything for goals it has seen.

    Each goal cell's padded static bytes (obstacle bit + its heuristic bits, and its padded
    distances for "cost_to_go") sit in one slot of a pool, searched once when the goal first
    appears; slots of goals no agent holds any more are kept for `spare` goals (goals repeat:
    idle robots, task stations) and reused least recently used first. Memory: one padded map
    (one byte a cell, three with distances on maps under 32,767 cells) per current goal plus `spare`.
    guidance: a `grid.guidance.Guidance` for the map: the heuristic bits (and distances) are the
    guided ones (`heuristic.DistanceTable`); None: BFS steps.

    A first tick's many new goals (whole searches writing `window_from` bytes or more, unguided)
    are first searched only in a window around the agent holding each (`WINDOW_MARGIN` cells
    beyond its field of view; `DistanceTable.open_windows`, exact): a goal is then searched whole
    before its agent's field of view leaves the window, the windows whose agents moved farthest
    first, enough each observation that all are whole within `WINDOW_MARGIN` observations
    (`grid.windows`).
    Observations are the same either way (a test).
    """

    def __init__(self, grid, radius: int = 4, observation: str = "paper", spare: int = 256,
                 guidance=None, window_from: int | None = None):
        from .heuristic import _as_grid, distance_table

        self.blocked = _as_grid(grid)
        self.guidance = guidance
        self.table = distance_table(self.blocked, guidance)
        self.channels = observation_channels(observation)
        self.observation = observation
        self.radius = r = int(radius)
        self.size = 2 * r + 1
        self.spare = max(int(spare), 0)
        h, w = self.blocked.shape
        self.hp, self.wp = h + 2 * r, w + 2 * r
        obstacle = np.ones((self.hp, self.wp), dtype=np.uint8)
        obstacle[r:r + h, r:r + w] = self.blocked
        self._obstacle = obstacle.reshape(-1)
        offsets = np.arange(self.size)
        self.window = (offsets[:, None] * self.wp + offsets[None, :]).reshape(-1)
        self.centre = r * self.wp + r
        self._static = np.empty((0, self.hp * self.wp), dtype=np.uint8)
        self._distances = None
        self._slot_of: dict[int, int] = {}  # goal flat cell -> slot, least recently used first
        self._free: list[int] = []
        self.searched = 0  # goals searched whole so far
        # windows (`DistanceTable.open_windows`): the FOV's offsets in one
        self.window_from = WINDOW_FROM_BYTES if window_from is None else int(window_from)
        self.margin = WINDOW_MARGIN
        self.half = r + self.margin
        self.wside = 2 * self.half + 1
        self.in_window = (offsets[:, None] * self.wside + offsets[None, :]).reshape(-1)
        self._window_of: set[int] = set()  # goals seen through the table's windows
        self._rate = 0  # windows searched whole each observation
        self.windowed = 0  # goals first searched in a window so far

    def _whole_bytes(self) -> int:
        """Bytes a goal's whole search writes: its distance row and the pool's maps."""
        cells = self.blocked.size
        row = 8 if self.table.guided else 2 if cells < np.iinfo(np.int16).max else 4
        pool = self.hp * self.wp * (1 + (self._distances_dtype().itemsize
                                         if self.channels > NUM_OBS_CHANNELS else 0))
        return cells * row + pool

    def _distances_dtype(self) -> np.dtype:
        # int16 while every distance fits (compact_distances' rule)
        fits = self.blocked.size < np.iinfo(np.int16).max
        return np.dtype(np.float32 if self.table.guided else np.int16 if fits else np.int32)

    def _grow(self, needed: int) -> None:
        old = self._static.shape[0]
        cap = max(needed, old + old // 2, 16)
        static = np.empty((cap, self.hp * self.wp), dtype=np.uint8)
        static[:old] = self._static
        self._static = static
        if self.channels > NUM_OBS_CHANNELS:
            dist = np.empty((cap, self.hp * self.wp), dtype=self._distances_dtype())
            if old:
                dist[:old] = self._distances
            self._distances = dist
        self._free.extend(range(cap - 1, old - 1, -1))

    def slots(self, goals) -> np.ndarray:
        """int64 (M,) the pool slots of `goals` (M, 2), searching whole the goals not in it."""
        from .heuristic import _as_goals

        w = self.blocked.shape[1]
        goals = _as_goals(goals, self.blocked.shape)
        flat = goals[:, 0] * w + goals[:, 1]
        unique = np.unique(flat).tolist()
        self._window_of.difference_update(unique)
        self._whole(unique, [g for g in unique if g not in self._slot_of])
        lookup = np.array([self._slot_of[g] for g in unique], dtype=np.int64)
        return lookup[np.searchsorted(np.asarray(unique, dtype=np.int64), flat)]

    def _whole(self, current: list[int], missing: list[int]) -> None:
        """Search `missing` whole into the pool; `current` (every goal held now) are kept."""
        slot_of = self._slot_of
        for g in current:  # most recently used last
            if g in slot_of:
                slot_of[g] = slot_of.pop(g)
        if not missing:
            return
        in_use = sum(1 for g in current if g in slot_of)
        keep = in_use + len(missing) + self.spare
        while len(slot_of) + len(missing) > keep:  # the least recently used goals go first
            self._free.append(slot_of.pop(next(iter(slot_of))))
        if len(self._free) < len(missing):
            self._grow(self._static.shape[0] + len(missing) - len(self._free))
        h, w = self.blocked.shape
        r = self.radius
        for start in range(0, len(missing), 256):  # bounded temporaries
            chunk = missing[start:start + 256]
            slots = [self._free.pop() for _ in chunk]
            # a batch: the compiled search on every core, writing the pool's slots itself
            self.table.prepare_static(chunk, [self._static[slot] for slot in slots], r)
            if self._distances is not None:
                dist = self.table.many(np.array([divmod(g, w) for g in chunk], np.int64))
            for k, (g, slot) in enumerate(zip(chunk, slots)):
                if self._distances is not None:
                    padded = self._distances[slot].reshape(self.hp, self.wp)
                    padded[:] = UNREACHABLE
                    padded[r:r + h, r:r + w] = dist[k]
                slot_of[g] = slot
        self.searched += len(missing)

    def _open_windows(self, goals: list[int], centres: np.ndarray) -> None:
        """Search `goals` in windows around `centres` (M, 2)."""
        # the pool's room for them now (untouched memory costs nothing yet): growing it by half
        # at each batch of upgrades would copy it again and again
        room = len(self._slot_of) + len(self._window_of) + len(goals) + self.spare
        if self._static.shape[0] < room:
            self._grow(room)
        self.table.open_windows(goals, centres, self.half)
        opened = [g for g in goals if self.table.windows.get(g) is not None]  # not whole already
        self._window_of.update(opened)
        self.windowed += len(opened)

    def _place(self, flat: np.ndarray, own: np.ndarray) -> list[int]:
        """Make every goal of `flat` (M,) observable for agents at `own` (M, 2): in the pool,
        or in a window that holds its agents' fields of view. Returns the unique goals."""
        unique, first = np.unique(flat, return_index=True)
        unique = unique.tolist()
        window_of = self._window_of
        if window_of:
            gone = window_of.difference(unique)  # nobody heads there any more
            self.table.windows.close(gone)
            window_of.difference_update(gone)
            # a conflict rule that read outside a window had the goal searched whole
            window_of.difference_update([g for g in window_of if self.table.windows.get(g) is None])
        new = [k for k, g in enumerate(unique) if g not in self._slot_of and g not in window_of]
        whole = [unique[k] for k in new]
        if whole and not self.table.guided \
                and len(whole) * self._whole_bytes() >= self.window_from:
            self._open_windows(whole, own[first[new]])
            self._rate = max(self._rate, -(-len(window_of) // self.margin))
            whole = [g for g in whole if g not in window_of]  # those searched whole already
            rate = 0  # this observation only windows: the first tick's time
        else:
            rate = self._rate
        if window_of:
            # how far each windowed goal's agents are from its window's centre
            held = np.fromiter((g in window_of for g in flat.tolist()), bool, len(flat))
            goals = flat[held]
            half = self.half
            centres = np.array([(w.row0 + half, w.col0 + half) for w in
                                map(self.table.windows.get, goals.tolist())], np.int64)
            moved = np.abs(own[held] - centres).max(axis=1)
            farthest: dict[int, int] = {}
            for g, m in zip(goals.tolist(), moved.tolist()):
                farthest[g] = max(farthest.get(g, 0), m)
            order = sorted(farthest, key=farthest.get, reverse=True)
            upgrade = order[:rate] + [g for g in order[rate:] if farthest[g] > self.margin]
            window_of.difference_update(upgrade)
            whole += upgrade
            if not window_of:
                self._rate = 0
        self._whole(unique, whole)
        return unique

    def observe(self, positions, goals, agents=None) -> np.ndarray:
        """float32 (M, C, S, S) of agents `agents` (M,) (None: all N) heading to `goals` (M, 2),
        given every agent's `positions` (N, 2): the other agents are seen in channel 0 too."""
        from .heuristic import _as_goals

        positions = check_positions(positions, self.blocked.shape)
        own = positions if agents is None else positions[np.asarray(agents, dtype=np.int64)]
        goals = np.asarray(goals)
        if goals.shape != (len(own), 2):
            raise ValueError(f"goals must have shape ({len(own)}, 2), got {goals.shape}")
        goals = _as_goals(goals, self.blocked.shape)
        flat = goals[:, 0] * self.blocked.shape[1] + goals[:, 1]
        self._place(flat, own)
        occupancy = np.zeros(self.hp * self.wp, dtype=np.uint8)
        occupancy[positions[:, 0] * self.wp + positions[:, 1] + self.centre] = 1
        corners = own[:, 0] * self.wp + own[:, 1]
        windows = corners[:, None] + self.window  # (M, S*S)
        cost_to_go = self.channels > NUM_OBS_CHANNELS
        pooled = np.fromiter((g in self._slot_of for g in flat.tolist()), bool, len(flat))
        if pooled.all():
            slots = np.array([self._slot_of[g] for g in flat.tolist()], np.int64)[:, None]
            static = self._static[slots, windows]
            dist = self._distances[slots, windows] if cost_to_go else None
        else:
            static = np.empty((len(own), self.size ** 2), np.uint8)
            dist = np.empty((len(own), self.size ** 2), np.int32) if cost_to_go else None
            if pooled.any():
                slots = np.array([self._slot_of[g] for g in flat[pooled].tolist()],
                                 np.int64)[:, None]
                static[pooled] = self._static[slots, windows[pooled]]
                if cost_to_go:
                    dist[pooled] = self._distances[slots, windows[pooled]]
            held = ~pooled
            seen = [self.table.windows.get(g) for g in flat[held].tolist()]
            corner = np.array([(w.row0, w.col0) for w in seen], np.int64)
            offset = own[held] - corner - self.radius  # the FOV's corner in the window
            inside = (offset[:, 0] * self.wside + offset[:, 1])[:, None] + self.in_window
            static[held] = np.take_along_axis(np.stack([w.static for w in seen]), inside, 1)
            if cost_to_go:
                dist[held] = np.take_along_axis(np.stack([w.dist for w in seen]), inside, 1)
        return _assemble(occupancy[windows], static, dist, self.channels, self.radius)


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
