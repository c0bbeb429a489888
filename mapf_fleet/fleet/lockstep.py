"""The lockstep bookkeeping the simulator and the aggregator share (plain Python, no rclpy: the
robots' messages are read by their fields).

Both nodes run the same tick: publish the fleet state of tick k, collect every robot's RobotMove
for k (its ranked actions; a move missing after `decision_timeout` is "stay" and reported),
arbitrate them (`arbiter.TickArbiter`, the configured conflict rule) and command the waypoints,
turn the commands into the positions of k + 1 (this is where they differ: the simulator takes
them, the aggregator waits for the real robots' poses), then report progress; at the end the
outcome and the run record. `FleetTicker` holds the per-tick decisions and readiness; the run
itself (cells, goals, tasks, arbiter, record) is the fleet core's `fleet.run.FleetRun`; the nodes
feed them messages and publish what they return.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from mapf_fleet.fleet import parameters
from mapf_fleet.fleet.arbiter import ranking_problem, single_choice_ranking
from mapf_fleet.fleet.instances import InstanceSource
from mapf_fleet.fleet.record import Decisions


def parameter_change_problem(name: str, value, table: dict) -> str:
    """Why parameter `name` of a node with parameter table `table` (fleet.parameters) may not
    become `value` at runtime ("" when it may)."""
    if name not in table:
        return f"{name}: no such parameter"
    if not table[name].runtime:
        runtime = ", ".join(parameters.runtime_names(table))
        return (f"{name}: read at start-up, cannot change during a run (restart the node with "
                f"-p {name}:=VALUE); changeable at runtime: {runtime}")
    problem = table[name].problem(value)
    return f"{name}: {problem}" if problem else ""


def instance_source(params: dict) -> InstanceSource:
    """The (validated) instance source named by a node's instance parameters."""
    return InstanceSource(params["instance_file"], params["map_file"], params["scen_file"],
                          int(params["num_robots"]), int(params["size"]),
                          float(params["density"]), int(params["seed"]),
                          float(params.get("cell_size", 0.0)))


def fleet_run(params: dict, grid, starts, goals, episode: int, series, geometry=None,
              start_tick: int = 0):
    """The node's `fleet.run.FleetRun` from its parameters (task source, tick limit, rule)."""
    from mapf_fleet.fleet.run import FleetRun
    from mapf_fleet.fleet.tasks import make_task_source

    seed = int(params["goal_seed"]) if int(params.get("goal_seed", -1)) >= 0 else \
        int(params.get("seed", 0))
    cell_of = None if geometry is None else geometry.xy_to_cell
    tasks = make_task_source(str(params["task_source"]), grid, seed=seed,
                             task_file=str(params["task_file"]), num_robots=len(starts),
                             cell_of=cell_of, starts=starts)
    from mapf_fleet.grid.guidance_made import GuidanceSource

    source = GuidanceSource.parse(params.get("guidance", "none"))
    # online guidance: the run steps the flow; the policy processes follow it from the states
    return FleetRun(grid, starts, tasks, goals, rule=str(params["conflict_rule"]),
                    max_steps=int(params["max_steps"]), episode=episode, series=series,
                    start_tick=start_tick,
                    planning_budget=float(params.get("planning_budget", 1.0)),
                    guidance=source.for_map(grid), flow=source.flow(grid))


def _batch_problem(n: int, prefs, received, counts, requested, missing_counts,
                   missing) -> str:
    """Why a RobotMoves of `n` robots is malformed ("" when it is not): its per-robot lists
    must match its robots and its counts the flattened lists."""
    if len(prefs) != 5 * n:
        return f"{len(prefs)} preferences for {n} robots (5 each)"
    for name, values in (("messages_received", received), ("requested_counts", counts),
                         ("missing_counts", missing_counts)):
        if len(values) != n:
            return f"{len(values)} {name} for {n} robots"
    if sum(counts) != len(requested):
        return f"requested_counts sum to {sum(counts)}, {len(requested)} requested"
    if sum(missing_counts) != len(missing):
        return f"missing_counts sum to {sum(missing_counts)}, {len(missing)} missing_peers"
    return ""


class EpisodeBinding:
    """Which run (episode) a policy hub serves, so that it never serves a foreign simulator.

    Rule: a hub binds to the episode of the first fleet state it receives and ignores the states
    of every other episode while bound. It is free again when its run ends (the state with
    `done`) or when no state of its episode has come for `timeout` seconds (its simulator is
    gone: killed, or its process ended); the next state of any episode then binds it. Its
    heartbeats report the bound episode (0 when free), and a simulator counts as ready only
    robots that are free or bound to its own episode (`FleetTicker.on_status`), so a second
    simulator in the same namespace waits for free robots instead of taking them mid-run.
    Separate fleets on one ROS_DOMAIN_ID belong in separate namespaces (`up --namespace`)."""

    def __init__(self, timeout: float):
        self.timeout = float(timeout)
        self.episode: int | None = None
        self._seen = 0.0

    def accept(self, episode: int, done: bool, now: float | None = None) -> bool:
        """Whether a state of `episode` is to be served (binding a free hub to it)."""
        now = time.monotonic() if now is None else now
        if (self.episode is not None and int(episode) != self.episode
                and now - self._seen < self.timeout):
            return False
        self.episode = None if done else int(episode)
        self._seen = now
        return True

    @property
    def reported(self) -> int:
        """The episode to report in heartbeats: the bound one, 0 when free."""
        return self.episode or 0


class FleetTicker:
    """The current tick, the moves received for it and the robots' readiness.

    The executor's callbacks call `on_move` / `on_status`; the node's tick thread calls
    `wait_ready`, `collect` and `advance`. `cond` guards all of it and is notified on every
    change, so a node may guard (and wait on) its own feeds with it too (the aggregator's poses).
    """

    def __init__(self, num_robots: int, episode: int, tick: int = 0):
        self.num_robots = int(num_robots)
        self.episode = int(episode)
        self.tick = int(tick)
        self.cond = threading.Condition()
        self._prefs: dict[int, list[int]] = {}  # robot -> its ranking (first = its action)
        self._comm: dict[int, tuple[list[int], int]] = {}  # robot -> (requested, received)
        self._ready_peers: dict[int, int] = {}
        self._hosts: dict[int, str] = {}  # robot -> the process hosting it (heartbeats)
        self.stopped = False  # stop(): the run ends (signal, failed callback), waits return

    def stop(self) -> None:
        """End the run: `wait_ready` and `collect` return at once, `run_lockstep` finishes with
        a "stopped at tick k" outcome. Any thread may call it."""
        with self.cond:
            self.stopped = True
            self.cond.notify_all()

    def on_move(self, msg) -> str | None:
        """Store a RobotMove (one robot's decision) of the current tick; a text to log as a
        warning, or None."""
        with self.cond:
            if msg.episode != self.episode or msg.tick != self.tick:
                return None  # stale tick or another run
            ranking = list(getattr(msg, "preferences", ()))  # the field keeps its wire name
            problem = self._store(int(msg.robot_id), int(msg.action), ranking,
                                  msg.requested, int(msg.messages_received))
            if problem:
                return problem
            self.cond.notify_all()
        if msg.missing_peers:
            return (f"tick {msg.tick}: robot {msg.robot_id} decided without peers "
                    f"{list(msg.missing_peers)} (timed out)")
        return None

    def on_moves(self, msg) -> str | None:
        """Store a RobotMoves (the decisions of every robot of one policy process) of the
        current tick; a text to log as a warning (a malformed batch, bad moves, robots that
        decided without some peers), or None."""
        ids = [int(r) for r in msg.robot_ids]
        n = len(ids)
        prefs = [int(a) for a in msg.preferences]
        counts, requested = list(msg.requested_counts), [int(j) for j in msg.requested]
        missing_counts, missing = list(msg.missing_counts), list(msg.missing_peers)
        problem = _batch_problem(n, prefs, list(msg.messages_received), counts, requested,
                                 missing_counts, missing)
        if problem:
            return f"ignored a malformed RobotMoves from {msg.host or 'a policy process'}: {problem}"
        problems, left_out = [], {}
        with self.cond:
            if msg.episode != self.episode or msg.tick != self.tick:
                return None  # stale tick or another run
            start = missing_start = 0
            for k, robot in enumerate(ids):
                ranking = prefs[5 * k:5 * k + 5]
                problem = self._store(robot, ranking[0], ranking,
                                      requested[start:start + counts[k]],
                                      int(msg.messages_received[k]))
                start += counts[k]
                if problem:
                    problems.append(problem)
                if missing_counts[k]:
                    left_out[robot] = [int(j) for j in
                                       missing[missing_start:missing_start + missing_counts[k]]]
                missing_start += missing_counts[k]
            self.cond.notify_all()
        lines = problems[:3] + ([f"and {len(problems) - 3} more"] if len(problems) > 3 else [])
        if left_out:
            lines.append(f"tick {msg.tick}: robots decided without peers {left_out} (timed out)")
        return "; ".join(lines) or None

    def _store(self, robot: int, action: int, ranking: list, requested, received: int) -> str:
        """Store one robot's decision (under `cond`); why it is ignored, "" when it is not."""
        if robot >= self.num_robots or action > 4:
            return f"ignored bad move {robot}/{action}"
        problem = ranking_problem(action, ranking)
        if problem:
            return f"ignored bad move of robot {robot}: {problem}"
        self._prefs[robot] = ([int(a) for a in ranking] if ranking
                              else single_choice_ranking(action))
        self._comm[robot] = ([int(j) for j in requested], int(received))
        return ""

    def on_status(self, msg) -> None:
        """A RobotStatus: one robot's heartbeat."""
        self._note_ready(int(getattr(msg, "episode", 0)), (int(msg.robot_id),), msg.ready,
                         int(msg.peers), str(getattr(msg, "host", "")))

    def on_hub_status(self, msg) -> None:
        """A HubStatus: the heartbeat of every robot of one policy process."""
        self._note_ready(int(msg.episode), [int(r) for r in msg.robot_ids], msg.ready,
                         int(msg.peers), str(msg.host))

    def _note_ready(self, episode: int, robots, ready: bool, peers: int, host: str) -> None:
        if episode not in (0, self.episode):
            return  # robots serving another simulator's run (EpisodeBinding) are not ours
        if not ready:
            return
        with self.cond:
            for robot in robots:
                if robot < self.num_robots:
                    self._ready_peers[robot] = peers
                    self._hosts[robot] = host
            self.cond.notify_all()

    def ready_hosts(self) -> int:
        """How many processes host the robots that reported ready (their heartbeats' host)."""
        with self.cond:
            return len(set(self._hosts.values()))

    def unready(self) -> list[int]:
        """Robots not (yet) reporting that they hear every robot (call with or without cond)."""
        with self.cond:
            ready = {r for r, peers in self._ready_peers.items() if peers >= self.num_robots}
        return sorted(set(range(self.num_robots)) - ready)

    def wait_ready(self, timeout: float, also=lambda: True) -> list[int]:
        """Wait until every robot is ready and `also()` (called under `cond`) holds, or
        `timeout` seconds; return the robots still not ready."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while time.monotonic() < deadline and not self.stopped:
                if not self.unready() and also():
                    break
                self.cond.wait(0.1)
        return self.unready()

    def collect(self, timeout: float) -> Decisions:
        """The moves of the current tick, waiting up to `timeout` seconds for all of them."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while len(self._prefs) < self.num_robots and not self.stopped:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self.cond.wait(remaining)
            prefs, comm = dict(self._prefs), dict(self._comm)
            self._prefs, self._comm = {}, {}
            tick = self.tick
        n = self.num_robots
        stay_first = list(range(5))
        rankings = np.array([prefs.get(i, stay_first) for i in range(n)],
                            dtype=np.int64).reshape(n, 5)
        return Decisions(tick=tick, actions=rankings[:, 0].copy(), rankings=rankings,
                         missing=sorted(set(range(n)) - set(prefs)),
                         requested=[comm.get(i, ([], 0))[0] for i in range(n)],
                         messages=[comm.get(i, ([], 0))[1] for i in range(n)])

    def advance(self) -> int:
        """Go on to the next tick; moves that came late for the old one are dropped."""
        with self.cond:
            self.tick += 1
            self._prefs, self._comm = {}, {}
            return self.tick
