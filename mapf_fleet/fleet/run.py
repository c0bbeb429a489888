"""One run of a fleet without ROS (numpy only): the fleet core.

A `FleetRun` owns the grid, the robots' cells, their goals and last actions, the tick's arbiter
(`arbiter.TickArbiter`, the conflict rule), the task source (`tasks`) and the recorder
(`record.RunRecorder`). One tick is

    resolution = run.resolve(decisions)            # the arbiter's commanded cells
    events = run.advance(decisions, positions, ...)  # the cells the robots are in now

(`run.step(decisions)` does both for a simulated fleet, whose robots are where they are
commanded). The simulator node, the real-robot aggregator and the evaluator's lifelong rollout
(`evaluation.lifelong`) are adapters around it, so the fleet and the evaluator cannot drift
apart.

Goals. Each robot is *active* (it has a goal: a cell to reach) or *idle* (no task: its goal is
the cell it is in, updated every tick, so an idle robot stays where it is and yields when a
busy robot needs its cell; PIBT pushes it like any robot on its goal). Goals change at tick
boundaries only: `request_goal` / `submit_task` / `cancel` check a request at once and return
what became of it, and the change is applied by the next `advance` (or `apply_requests` while
the fleet is idle), so every robot decides a tick with the goals of that tick's state. A new
goal puts the robot's PIBT priority back to its tie-breaker (`PIBTShield.set_goals`: priority
counts the time waited for the current goal).

Goal rules (a request is rejected with the reason, the run goes on): the robot must exist; the
cell must be on the map, free, and reachable from the robot's cell; and no other robot may
already be headed for it (an active goal, or one requested this tick), since two robots cannot
both stop on one cell. Goals drawn by the lifelong source are exempt from the last rule (module
`tasks`). "Any robot" tasks go to the nearest idle robot by path distance (the map's distances
under the guidance, `fleet_map.FleetMap`; ties: the lower id), and wait in a queue while no
robot is idle.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from .arbiter import DEFAULT_CONFLICT_RULE, Resolution, TickArbiter
from .fleet_map import FleetMap
from .outcome import RunReport
from .record import Decisions, GoalEvent, RunRecorder
from .tasks import Task, TaskSource, batch_problems


class FleetRun(RunReport):
    """A fleet on one map: see the module docstring.

    grid (H, W) nonzero = obstacle; starts (N, 2) cells; goals (N, 2) the instance's goals (for
    the instance and lifelong sources; None otherwise); tasks: a `TaskSource`; max_steps: the tick
    limit (0: none, a continuous run until stopped); series: the adapter's own per-tick record
    entries ("executed", "overridden" and "collided" are filled in by `step`); guidance: a
    `grid.guidance.Guidance` for the map (None: BFS distances), read by the rule and every
    distance the run takes; flow: a `grid.guidance_made.CongestionFlow` that updates the
    guidance from the robots' moves as the run goes (online guidance).
    """

    def __init__(self, grid, starts, tasks: TaskSource, goals=None, *,
                 rule: str = DEFAULT_CONFLICT_RULE, max_steps: int = 256, episode: int = 0,
                 start_tick: int = 0, series=(), planning_budget: float | None = None,
                 guidance=None, flow=None):
        self.grid = np.asarray(grid) != 0
        self.positions = np.array(starts, dtype=np.int64).reshape(-1, 2)
        self.num_robots = len(self.positions)
        self.tasks = tasks
        if int(max_steps) < 0 or (int(max_steps) == 0 and not tasks.continuous):
            raise ValueError(f"max_steps must be > 0 (0: no limit, continuous task sources "
                             f"only), got {max_steps}")
        self.max_steps = int(max_steps)
        self.goals, self.active = tasks.initial(self.positions, goals)
        self.goal_ids = [f"{tasks.name}-{i}-0" if self.active[i] else ""
                         for i in range(self.num_robots)]
        self.goal_sources = [tasks.name if self.active[i] else "" for i in range(self.num_robots)]
        self._goal_count = np.ones(self.num_robots, dtype=np.int64)  # ids of drawn goals
        self._task_of: list[tuple[Task, int] | None] = [None] * self.num_robots  # (task, stage)
        self.queue: deque[Task] = deque(tasks.initial_tasks())
        self.last_actions = np.full(self.num_robots, -1, dtype=np.int64)  # -1: none yet
        self.tick = int(start_tick)
        self.steps = 0
        self.goals_reached = 0
        self.reached_per_robot = np.zeros(self.num_robots, dtype=np.int64)
        self.tasks_done = np.zeros(self.num_robots, dtype=np.int64)
        self._requests: dict[int, tuple[tuple[int, int] | None, str, str]] = {}  # robot -> req
        # every distance of the run (goal checks, "any robot" tasks, the rule) from the map's
        # shared table under the guidance graph
        self.guidance = guidance
        self.flow = flow
        self.map = FleetMap(self.grid, guidance)
        self._counted: set[str] = set()  # one-shot goals whose arrival was counted
        self._evacuating: dict[int, tuple[int, int]] = {}  # idle robot -> cell it clears to
        self.arbiter = TickArbiter(self.grid, self.goals, rule, planning_budget, guidance)
        self.recorder = RunRecorder(episode, self.num_robots, self.max_steps, series=series,
                                    conflict_rule=rule, task_source=tasks.name)
        # goal changes of the tick boundaries since the adapter last took them (`advance`,
        # `apply_requests`); a request's own answer is returned to its caller instead
        self.pending_events: list[GoalEvent] = []
        self._emit([GoalEvent(self.tick, i, "assigned", tuple(self.goals[i].tolist()),
                              tasks.name, self.goal_ids[i])
                    for i in range(self.num_robots) if self.active[i]])
        self._assign_queued()
        self._sync_goals()
        self.recorder.start(self.positions, self.goals)

    # ---- state ---------------------------------------------------------------------------------
    @property
    def rule(self) -> str:
        return self.arbiter.rule

    def on_goal(self) -> np.ndarray:
        return (self.positions == self.goals).all(axis=1)

    @property
    def idle(self) -> np.ndarray:
        return ~self.active

    @property
    def busy(self) -> int:
        return int(self.active.sum())

    def finished(self) -> str:
        """Why the run ends now ("" while it goes on)."""
        if self.max_steps and self.steps >= self.max_steps:
            return f"tick limit {self.max_steps}"
        if not self.tasks.continuous:
            if self.on_goal().all() and not self.queue and not self._requests:
                return "every robot on its goal"
        elif self.tasks.done(len(self.queue) + len(self._requests), self.busy):
            return "every task done"
        return ""

    @property
    def waiting(self) -> bool:
        """Nothing to do: every robot idle (or on its kept goal) and no request queued; a
        continuous fleet may sleep until a goal comes instead of ticking."""
        return (self.tasks.continuous and not self.active.any() and not self.queue
                and not self._requests)

    @property
    def throughput(self) -> float:
        """Goals reached per tick (POGEMA's average throughput)."""
        return self.goals_reached / self.steps if self.steps else 0.0

    # ---- goals at run time --------------------------------------------------------------------
    def set_guidance(self, guidance) -> None:
        """Every distance of the run (the rule's, goal checks) under `guidance` from now on."""
        self.guidance = guidance
        self.map.set_guidance(guidance)
        self.arbiter.set_guidance(guidance)

    def goal_problem(self, robot, cell, *, ignore_robot: int | None = None) -> str:
        """Why `cell` cannot be `robot`'s goal now ("" when it can); robot None: any robot."""
        h, w = self.grid.shape
        if robot is not None and not (isinstance(robot, (int, np.integer))
                                      and 0 <= int(robot) < self.num_robots):
            return f"unknown robot {robot!r} (robots 0..{self.num_robots - 1})"
        r, c = int(cell[0]), int(cell[1])
        if not (0 <= r < h and 0 <= c < w):
            return f"cell ({r}, {c}) is off the {h}x{w} map"
        if self.grid[r, c]:
            return f"cell ({r}, {c}) is an obstacle"
        if robot is not None:
            here = self.positions[int(robot)]
            if not self.map.reaches(here, (r, c)):
                return (f"cell ({r}, {c}) is unreachable from robot {int(robot)}'s cell "
                        f"({int(here[0])}, {int(here[1])})")
        for j in range(self.num_robots):
            if j in (robot, ignore_robot):
                continue
            asked = self._requests.get(j)
            target = asked[0] if asked is not None else (
                tuple(self.goals[j].tolist()) if self.active[j] else None)
            if target is not None and tuple(int(v) for v in target) == (r, c):
                return f"robot {j} is already headed for cell ({r}, {c})"
        return ""

    def request_goal(self, robot: int, cell, source: str, goal_id: str = "") -> GoalEvent:
        """Send `robot` to `cell` from the next tick on (preempting its goal); the event says
        "accepted" or "rejected" with the reason (recorded; the caller publishes it). The goal's
        `assigned` / `reached` / `preempted` / ... events follow from `advance`."""
        problem = self.goal_problem(robot, cell)
        cell_t = None if cell is None else (int(cell[0]), int(cell[1]))
        if problem:
            event = GoalEvent(self.tick, int(robot) if isinstance(robot, (int, np.integer))
                              and 0 <= int(robot) < self.num_robots else -1,
                              "rejected", cell_t, source, goal_id, problem)
            self.recorder.add_events([event])
            return event
        self._requests[int(robot)] = (cell_t, source, goal_id)
        return GoalEvent(self.tick, int(robot), "accepted", cell_t, source, goal_id)

    def cancel(self, robot: int, goal_id: str = "", source: str = "cancel") -> GoalEvent:
        """Stop `robot` where it is (it becomes idle) from the next tick; with `goal_id`, only if
        that is its current or requested goal."""
        if not (isinstance(robot, (int, np.integer)) and 0 <= int(robot) < self.num_robots):
            return GoalEvent(self.tick, -1, "rejected", None, source, goal_id,
                             f"unknown robot {robot!r}")
        robot = int(robot)
        asked = self._requests.get(robot)
        current = asked[2] if asked is not None else self.goal_ids[robot]
        if goal_id and goal_id != current:
            return GoalEvent(self.tick, robot, "rejected", None, source, goal_id,
                             f"not robot {robot}'s goal (its goal is {current or 'none'})")
        self._requests[robot] = (None, source, goal_id or current)
        return GoalEvent(self.tick, robot, "accepted", None, source, goal_id or current)

    def has_goal(self, robot: int) -> bool:
        """Whether `robot` has a goal now, or one requested for the next tick (a cancel: no)."""
        asked = self._requests.get(int(robot))
        return bool(self.active[int(robot)]) if asked is None else asked[0] is not None

    def submit_task(self, task: Task) -> GoalEvent:
        """Queue a task (for its robot, or the nearest idle robot); checked now."""
        return self.submit_tasks([task])[0]

    def submit_tasks(self, tasks) -> list[GoalEvent]:
        """Queue every task or none (`tasks.batch_problems`: each checked before any is
        queued, so a request resent after a fix does not queue its good tasks twice)."""
        problems = batch_problems(self, tasks)
        events = [GoalEvent(self.tick, -1 if t.robot is None or not 0 <= t.robot < self.num_robots
                            else t.robot, "rejected" if problems else "queued", t.goals[0],
                            t.source, t.task_id, problems.get(k, "")) for k, t in enumerate(tasks)]
        if not problems:
            self.queue.extend(tasks)
        self.recorder.add_events(events)
        return events

    def apply_requests(self) -> list[GoalEvent]:
        """Apply the goal requests and queued tasks now (between ticks); the new events."""
        self._apply_requests()
        self._assign_queued()
        self._sync_goals()
        return self.take_events()

    def take_events(self) -> list[GoalEvent]:
        events, self.pending_events = self.pending_events, []
        return events

    # ---- ticks --------------------------------------------------------------------------------
    def resolve(self, decisions: Decisions, held=None, reserved=()) -> Resolution:
        """The arbiter's commands for this tick (robots `decisions.missing` are held)."""
        held = np.zeros(self.num_robots, dtype=bool) if held is None else \
            np.asarray(held, dtype=bool).copy()
        held[list(decisions.missing)] = True
        return self.arbiter.resolve(self.positions, decisions.rankings, held=held,
                                    reserved=reserved)

    def step(self, decisions: Decisions, **series) -> tuple[Resolution, list[GoalEvent]]:
        """A simulated tick: resolve, and the robots are where they were commanded. DCC's last
        action is the executed one under a shield (the evaluator's `policy.executed`) and the
        robot's own choice under the paper's rule (`MAPFEnv.last_actions`)."""
        result = self.resolve(decisions)
        last = result.actions if self.arbiter.shield is not None else decisions.actions
        # the resolution's own series, where the recorder keeps them and the caller did not
        own = {"executed": result.actions.tolist(), "overridden": result.overridden_ids,
               "collided": result.collided_ids}
        series = {**{k: v for k, v in own.items() if k in self.recorder.series}, **series}
        events = self.advance(decisions, result.positions, last,
                              collisions=int(result.collided.sum()), **series)
        return result, events

    def advance(self, decisions: Decisions, positions, last_actions, *, collisions: int = 0,
                **series) -> list[GoalEvent]:
        """The robots are in `positions` after the tick of `decisions`: record it, count the
        arrivals, hand out next goals and apply the requests; the events of this tick."""
        before, self.positions = self.positions, np.asarray(positions, dtype=np.int64).copy()
        self.last_actions = np.asarray(last_actions, dtype=np.int64).copy()
        if self.flow is not None:  # online guidance: the next ticks read the updated costs
            guidance = self.flow.step(before, self.positions)
            if guidance is not None:
                self.set_guidance(guidance)
        self.tick += 1
        self.steps += 1
        self.recorder.add_tick(decisions, self.positions, collisions, **series)
        self._arrivals()
        self._apply_requests()
        self._assign_queued()
        self._sync_goals()
        events = self.take_events()
        self.recorder.end_tick()
        return events

    def _arrivals(self) -> None:
        """Active robots on their goals: count the arrival and move each on (its task's next
        goal; the lifelong source's next goal; idle), or, one-shot, let it keep its goal."""
        for i in np.flatnonzero(self.active & self.on_goal()).tolist():
            keep = self.tasks.keeps_goal() and self._task_of[i] is None
            if keep and self.goal_ids[i] in self._counted:
                continue  # one-shot: already counted, it stays on its goal
            cell = tuple(self.goals[i].tolist())
            self.goals_reached += 1
            self.reached_per_robot[i] += 1
            self._emit([GoalEvent(self.tick, i, "reached", cell, self.goal_sources[i],
                                  self.goal_ids[i])])
            if keep:
                self._counted.add(self.goal_ids[i])
                continue
            task = self._task_of[i]
            if task is not None and task[1] + 1 < len(task[0].goals):
                task, stage = task[0], task[1] + 1
                self._task_of[i] = (task, stage)
                self._set_goal(i, task.goals[stage], task.source, f"{task.task_id}/{stage}",
                               announce_previous=False)
                continue
            self._task_of[i] = None
            if self.tasks.draws_goals and self.queue and self._take_queued(i):
                continue  # a lifelong robot is never idle: it takes a waiting task first
            nxt = self.tasks.next_goal(i, cell)  # lifelong: the next goal, else None
            if nxt is not None:
                self._goal_count[i] += 1
                self._set_goal(i, nxt, self.tasks.name,
                               f"{self.tasks.name}-{i}-{self._goal_count[i] - 1}",
                               announce_previous=False)
                continue
            self.tasks_done[i] += 1
            self._set_idle(i)

    def _apply_requests(self) -> None:
        requests, self._requests = self._requests, {}
        for robot, (cell, source, goal_id) in sorted(requests.items()):
            if cell is None:  # cancel
                if self.active[robot]:
                    self._emit([GoalEvent(self.tick, robot, "cancelled",
                                          tuple(self.goals[robot].tolist()),
                                          self.goal_sources[robot], self.goal_ids[robot],
                                          "cancelled: the robot holds its cell")])
                    self._task_of[robot] = None
                    self._set_idle(robot)
                continue
            problem = self.goal_problem(robot, cell)  # the fleet moved since the request
            if problem:
                self._emit([GoalEvent(self.tick, robot, "rejected", cell, source, goal_id,
                                      problem)])
                continue
            self._task_of[robot] = None
            self._set_goal(robot, cell, source, goal_id or f"{source}-{robot}-{self.tick}")

    def _assign_queued(self) -> None:
        """Hand queued tasks to idle robots, in queue order."""
        if not self.queue:
            return
        waiting = deque()
        while self.queue:
            task = self.queue.popleft()
            robot = self._robot_for(task)
            if robot is None:
                waiting.append(task)
                continue
            self._task_of[robot] = (task, 0)
            self._set_goal(robot, task.goals[0], task.source,
                           task.task_id if len(task.goals) == 1 else f"{task.task_id}/0")
        self.queue = waiting

    def _take_queued(self, robot: int) -> bool:
        """Give `robot`, free between two drawn goals, the first waiting task it can take."""
        here = self.positions[robot]
        for task in self.queue:
            first = task.goals[0]
            if task.robot not in (None, robot) or not self.map.reaches(here, first) \
                    or self.goal_problem(None, first).startswith("robot "):
                continue
            self.queue.remove(task)
            self._task_of[robot] = (task, 0)
            self._set_goal(robot, first, task.source,
                           task.task_id if len(task.goals) == 1 else f"{task.task_id}/0",
                           announce_previous=False)
            return True
        return False

    def _robot_for(self, task: Task) -> int | None:
        first = task.goals[0]
        if self.goal_problem(None, first).startswith("robot "):
            return None  # someone is headed there: wait until it moves on
        if task.robot is not None:
            ok = not self.active[task.robot] and task.robot not in self._requests
            return task.robot if ok else None
        idle = [i for i in np.flatnonzero(~self.active).tolist() if i not in self._requests]
        if not idle:
            return None
        return self.map.nearest(idle, self.positions[idle], first)  # ties: the lower id

    def _set_goal(self, robot: int, cell, source: str, goal_id: str,
                  announce_previous: bool = True) -> None:
        if self.active[robot] and announce_previous:  # it had a goal it did not reach
            self._emit([GoalEvent(self.tick, robot, "preempted", tuple(self.goals[robot].tolist()),
                                  self.goal_sources[robot], self.goal_ids[robot],
                                  f"preempted by {goal_id or 'a new goal'} ({source})")])
        self.goals[robot] = (int(cell[0]), int(cell[1]))
        self.active[robot] = True
        self._evacuating.pop(robot, None)
        self.goal_sources[robot] = source
        self.goal_ids[robot] = goal_id
        self._emit([GoalEvent(self.tick, robot, "assigned", (int(cell[0]), int(cell[1])), source,
                              goal_id)])

    def _set_idle(self, robot: int) -> None:
        self.active[robot] = False
        self.goal_sources[robot] = ""
        self.goal_ids[robot] = ""

    def _sync_goals(self) -> None:
        """Idle robots' goals, then the arbiter's goals (and the evacuating robots' priority)."""
        boost = self._follow_idle()
        self.arbiter.set_goals(self.goals)
        self.arbiter.boost(boost)

    def _follow_idle(self) -> list[int]:
        """An idle robot's goal is the cell it stands in: it stays, and yields when a busy robot
        needs its cell. An idle robot standing on a busy robot's goal is sent instead to the
        nearest free cell that is neither a busy robot's goal nor a robot's cell (sticky until
        it gets there) with the top PIBT priority: in a dead end the busy robot could otherwise
        never get in (PIBT's reachability needs every cell on a cycle; a dead end has none, and
        the robot heading in would push the idle one deeper). Returns the robots to boost."""
        boost = []
        idle = np.flatnonzero(~self.active).tolist()
        if not idle:
            return boost
        busy_goals = {tuple(g) for g in self.goals[self.active].tolist()}
        occupied = {tuple(p) for p in self.positions.tolist()}
        for i in idle:
            here = tuple(self.positions[i].tolist())
            target = self._evacuating.get(i)
            if target is not None and (target == here or target in busy_goals):
                target = None
                del self._evacuating[i]
            if target is None and here in busy_goals:
                target = self.map.parking_cell(here, busy_goals | occupied)
                if target is not None:
                    self._evacuating[i] = target
                    boost.append(i)
            self.goals[i] = target if target is not None else here
        return boost

    def note(self, events) -> None:
        """Record events decided outside the run (a goal the ROS side refused before asking)."""
        self.recorder.add_events(events)

    def _emit(self, events) -> None:
        events = list(events)
        self.pending_events.extend(events)
        self.recorder.add_events(events)

    # ---- the end ------------------------------------------------------------------------------
    def abort_active(self, reason: str) -> list[GoalEvent]:
        """The run ends: every active goal given at run time (a request, a task) is aborted
        (events); the source's own endless stream (lifelong) just stops."""
        events = [GoalEvent(self.tick, i, "aborted", tuple(self.goals[i].tolist()),
                            self.goal_sources[i], self.goal_ids[i], reason)
                  for i in np.flatnonzero(self.active).tolist()
                  if not self.on_goal()[i] and (self.goal_sources[i] != self.tasks.name
                                                or self._task_of[i] is not None)]
        self._emit(events)
        return events
