"""FOV observations of agents whose goals change (a lifelong run, a fleet process):
`GoalObserver`, the goal-keyed pool of padded maps, and its windows for a first tick at scale.
The observation itself (its channels, `assemble`) is `grid.observation`'s."""

from __future__ import annotations

import numpy as np

from .heuristic import UNREACHABLE
from .observation import NUM_OBS_CHANNELS, assemble, check_positions, observation_channels


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
    (`grid.windows`). Those searches run on a thread of the observer's beside the rest of the
    tick (the network, the rule: the search releases the GIL) and join the pool at the next
    observation; a window about to be left is searched whole at once.
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
        self._pending = None  # whole searches running beside the tick (`_upgrade`)
        self._worker = None
        self._soon: list[int] = []  # windows to search whole beside this tick
        self._place_unique: list[int] = []
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
        self._land()
        self._window_of.difference_update(unique)
        self._whole(unique, [g for g in unique if g not in self._slot_of])
        lookup = np.array([self._slot_of[g] for g in unique], dtype=np.int64)
        return lookup[np.searchsorted(np.asarray(unique, dtype=np.int64), flat)]

    def _whole(self, current: list[int], missing: list[int]) -> None:
        """Search `missing` whole into the pool; `current` (every goal held now) are kept."""
        if missing:
            slots = self._reserve(current, len(missing))
            self._fill(missing, slots)
            self._commit(missing, slots)
        else:
            self._reserve(current, 0)

    def _reserve(self, current: list[int], count: int) -> list[int]:
        """`count` free pool slots, taken now; `current` (every goal held now) are kept, the
        least recently used other goals give theirs up first."""
        slot_of = self._slot_of
        for g in current:  # most recently used last
            if g in slot_of:
                slot_of[g] = slot_of.pop(g)
        if not count:
            return []
        in_use = sum(1 for g in current if g in slot_of)
        keep = in_use + count + self.spare
        while len(slot_of) + count > keep:
            self._free.append(slot_of.pop(next(iter(slot_of))))
        if len(self._free) < count:
            self._grow(self._static.shape[0] + count - len(self._free))
        return [self._free.pop() for _ in range(count)]

    def _fill(self, goals: list[int], slots: list[int]) -> None:
        """Search `goals` whole into their pool `slots` (writes nothing else of the observer's:
        it may run beside the rest of a tick, `_upgrade`)."""
        h, w = self.blocked.shape
        r = self.radius
        for start in range(0, len(goals), 256):  # bounded temporaries
            chunk, where = goals[start:start + 256], slots[start:start + 256]
            # a batch: the compiled search on every core, writing the pool's slots itself
            self.table.prepare_static(chunk, [self._static[slot] for slot in where], r)
            if self._distances is not None:
                dist = self.table.many(np.array([divmod(g, w) for g in chunk], np.int64))
                for k, slot in enumerate(where):
                    padded = self._distances[slot].reshape(self.hp, self.wp)
                    padded[:] = UNREACHABLE
                    padded[r:r + h, r:r + w] = dist[k]

    def _commit(self, goals: list[int], slots: list[int]) -> None:
        for g, slot in zip(goals, slots):
            self._slot_of[g] = slot
        self.searched += len(goals)

    def _upgrade(self, current: list[int], goals: list[int]) -> None:
        """Search windowed `goals` whole on a thread of its own, beside the rest of the tick
        (the network, the rule: the search releases the GIL); they move into the pool at the
        next observation (`_land`), their windows serving until then."""
        if not goals:
            return
        from concurrent.futures import ThreadPoolExecutor

        slots = self._reserve(current, len(goals))
        if self._worker is None:
            self._worker = ThreadPoolExecutor(1, thread_name_prefix="goal-search")
        self._pending = (self._worker.submit(self._fill, goals, slots), goals, slots)

    def _land(self) -> None:
        """The whole searches `_upgrade` started: wait for them, then take them into the pool."""
        if self._pending is None:
            return
        job, goals, slots = self._pending
        self._pending = None
        job.result()  # (its exception, if any, here)
        self._commit(goals, slots)
        self._window_of.difference_update(goals)

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
        self._land()
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
            # a window about to be left is searched whole now; `rate` more beside the tick
            must = [g for g in order if farthest[g] > self.margin]
            self._soon = [g for g in order[:rate] if farthest[g] <= self.margin]
            window_of.difference_update(must)
            whole += must
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
        self._place_unique = self._place(flat, own)
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
        if self._soon:  # after the gather: the searches close the windows they replace
            self._upgrade(self._place_unique, self._soon)
            self._soon = []
        return assemble(occupancy[windows], static, dist, self.channels, self.radius)
