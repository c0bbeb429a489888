"""Where a fleet's goals come from (numpy only): the task sources of `FleetRun`.

A *goal* is a cell a robot is sent to; a *task* is one goal, or a pick-up and a drop-off in
that order, for a named robot or for "any idle robot". Sources (`TASK_SOURCES`):

  instance  the classic one-shot episode: every robot has its instance goal from the start and
            keeps it; the run ends when all robots stand on their goals at once.
  lifelong  POGEMA's lifelong MAPF (`on_target: restart`): the first goals are the instance's;
            on arrival a robot draws its next goal, a free cell of its own connected region.
            Robot i's k-th goal depends only on (seed, i, k) (its own generator), so the same
            seed gives every policy the same goal sequence; goals of two robots may coincide, as
            in POGEMA (one of them arrives first and moves on).
  tasks     a task list (YAML, `load_task_file`): robots start idle; each task goes to its
            robot, or to the nearest idle robot by path distance, when that robot is idle; the
            run ends when every task is done.
  external  robots start idle on their start cells and move only for goals given at run time
            (ROS `goal_pose`, the `navigate_to_pose` action, the fleet's task service).

Goals given at run time (`FleetRun.request_goal`) work with every source. Tasks submitted at
run time (`FleetRun.submit_tasks`, queued whole or not at all) go to idle robots; under lifelong
a robot that reaches its goal takes the first waiting task before drawing its next goal; the
instance source refuses them at once (its robots keep their goals for the whole run: none is
ever free), and a run never succeeds while a task it accepted is still queued.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

TASK_SOURCES = ("instance", "lifelong", "tasks", "external")


class TaskFileError(ValueError):
    """A task file (or a task request) that cannot be used: names the file, the task and the
    field."""


@dataclass(frozen=True)
class Task:
    """`goals`: the cells to visit in order (one goal, or pick-up then drop-off); `robot`: the
    robot it is for, None for the nearest idle robot; `task_id`: how events name it."""

    goals: tuple[tuple[int, int], ...]
    robot: int | None = None
    task_id: str = ""
    source: str = "tasks"


@dataclass
class TaskSource:
    """The instance source and the base of the others: initial goals and what an arrival does."""

    name: str = "instance"
    # False: the run ends when every robot stands on its goal; True: it runs on (max_steps,
    # a stop, or `done` of the source)
    continuous: bool = False
    # True: a robot that arrives draws its next goal (it is never idle), so it takes a waiting
    # task first (`FleetRun._take_queued`)
    draws_goals: bool = False

    def initial(self, starts: np.ndarray, goals: np.ndarray | None):
        """(goals (N, 2), active (N,) bool): a robot without a task is idle (inactive)."""
        if goals is None:
            raise ValueError(f"task source {self.name!r} needs the instance's goals")
        return np.asarray(goals, dtype=np.int64).copy(), np.ones(len(starts), dtype=bool)

    def next_goal(self, robot: int, reached: tuple[int, int]) -> tuple[int, int] | None:
        """A robot's next goal after it reached `reached` (None: it keeps that goal / idles)."""
        return None

    def keeps_goal(self) -> bool:
        """Whether a robot that arrives keeps its goal (one-shot MAPF) instead of idling."""
        return True

    def initial_tasks(self) -> list[Task]:
        return []

    def done(self, queued: int, busy: int) -> bool:
        """Whether the source has nothing more to hand out (continuous sources only)."""
        return False


@dataclass
class InstanceTasks(TaskSource):
    name: str = "instance"
    continuous: bool = False


@dataclass
class LifelongTasks(TaskSource):
    """A new goal on arrival, from each robot's own seeded generator (module docstring)."""

    grid: np.ndarray | None = None
    seed: int = 0
    name: str = "lifelong"
    continuous: bool = True
    draws_goals: bool = True
    _regions: dict = field(default_factory=dict, init=False, repr=False)
    _rngs: dict = field(default_factory=dict, init=False, repr=False)
    _labels: np.ndarray | None = field(default=None, init=False, repr=False)

    def __post_init__(self):
        from scipy.ndimage import label

        free = np.asarray(self.grid) == 0
        self._labels, _ = label(free)  # 4-connected regions of free cells

    def initial(self, starts, goals):
        if goals is None:  # no instance goals: the first goal is drawn too
            goals = np.array([self._draw(i, tuple(map(int, s))) for i, s in enumerate(starts)])
        self._starts = np.asarray(starts, dtype=np.int64)
        return np.asarray(goals, dtype=np.int64).copy(), np.ones(len(starts), dtype=bool)

    def keeps_goal(self) -> bool:
        return False

    def next_goal(self, robot, reached):
        return self._draw(robot, reached)

    def _draw(self, robot: int, avoid: tuple[int, int]) -> tuple[int, int]:
        rng = self._rngs.get(robot)
        if rng is None:
            rng = self._rngs[robot] = np.random.default_rng([int(self.seed), int(robot)])
        cells = self._region_cells(robot, avoid)
        if len(cells) < 2:
            return avoid  # a region of one cell: nowhere else to go
        while True:  # draws depend on the robot's own history only (never on the policy)
            cell = tuple(int(v) for v in cells[rng.integers(len(cells))])
            if cell != tuple(avoid):
                return cell

    def _region_cells(self, robot: int, cell: tuple[int, int]) -> np.ndarray:
        region = int(self._labels[cell[0], cell[1]])
        found = self._regions.get(region)
        if found is None:
            found = self._regions[region] = np.argwhere(self._labels == region)
        return found


@dataclass
class TaskListTasks(TaskSource):
    """The tasks of a task file, handed to robots as they become idle."""

    tasks: list = field(default_factory=list)
    name: str = "tasks"
    continuous: bool = True

    def initial(self, starts, goals):
        return np.asarray(starts, dtype=np.int64).copy(), np.zeros(len(starts), dtype=bool)

    def keeps_goal(self) -> bool:
        return False

    def initial_tasks(self):
        return list(self.tasks)

    def done(self, queued, busy):
        return queued == 0 and busy == 0


@dataclass
class ExternalTasks(TaskSource):
    name: str = "external"
    continuous: bool = True

    def initial(self, starts, goals):
        return np.asarray(starts, dtype=np.int64).copy(), np.zeros(len(starts), dtype=bool)

    def keeps_goal(self) -> bool:
        return False


def make_task_source(name: str, grid=None, *, seed: int = 0, task_file: str = "",
                     num_robots: int | None = None, cell_of=None, starts=None) -> TaskSource:
    """The source called `name` (one of TASK_SOURCES). `task_file` for "tasks" (with `grid`
    and `starts`, every task is checked reachable); `seed` for "lifelong"; `cell_of(x, y)`
    turns metres into cells for task files that give `xy`."""
    if name not in TASK_SOURCES:
        raise ValueError(f"task_source must be one of {TASK_SOURCES}, got {name!r}")
    if name == "tasks" and not task_file:
        raise ValueError("task_source 'tasks' needs a task file (task_file / --task-source "
                         "tasks FILE)")
    if name != "tasks" and task_file:
        raise ValueError(f"task_file {task_file!r} is only read with task_source 'tasks', "
                         f"not {name!r}")
    if name == "instance":
        return InstanceTasks()
    if name == "lifelong":
        return LifelongTasks(grid=np.asarray(grid), seed=int(seed))
    if name == "external":
        return ExternalTasks()
    return TaskListTasks(tasks=load_task_file(task_file, num_robots=num_robots, cell_of=cell_of,
                                              grid=grid, starts=starts))


# ---- task files -------------------------------------------------------------------------------

def parse_tasks(entries, where: str, *, num_robots: int | None = None, cell_of=None,
                source: str = "tasks", first_id: int = 0) -> list[Task]:
    """Tasks from a list of mappings, each one of
        {goal: [row, col]}                        a goal for the nearest idle robot
        {goal: [row, col], robot: 3}              a goal for robot 3
        {pickup: [row, col], dropoff: [row, col]} (optionally robot: 3) two goals in order
        {xy: [x, y]} / {pickup_xy: ..., dropoff_xy: ...}   the same in metres (map frame)
    and an optional `id` (default: `source`-n, n counting from `first_id`). `where` names the
    file (or request) in errors."""
    if not isinstance(entries, list):
        raise TaskFileError(f"{where}: expected a list of tasks, got {type(entries).__name__}")
    tasks = []
    for k, entry in enumerate(entries):
        here = f"{where}: task {k}"
        if not isinstance(entry, dict):
            raise TaskFileError(f"{here}: expected a mapping with goal or pickup/dropoff, got "
                                f"{entry!r}")
        known = {"goal", "xy", "pickup", "dropoff", "pickup_xy", "dropoff_xy", "robot", "id"}
        unknown = sorted(set(entry) - known)
        if unknown:
            raise TaskFileError(f"{here}: unknown field {unknown[0]!r} (fields: "
                                f"{', '.join(sorted(known))})")
        goals = []
        if "goal" in entry or "xy" in entry:
            goals.append(_task_cell(entry, "goal", "xy", here, cell_of))
            if {"pickup", "dropoff", "pickup_xy", "dropoff_xy"} & set(entry):
                raise TaskFileError(f"{here}: give either goal or pickup/dropoff, not both")
        else:
            for name in ("pickup", "dropoff"):
                if name not in entry and f"{name}_xy" not in entry:
                    raise TaskFileError(f"{here}: missing field 'goal' (or 'pickup' and "
                                        f"'dropoff')")
                goals.append(_task_cell(entry, name, f"{name}_xy", here, cell_of))
        robot = entry.get("robot")
        if robot is not None:
            if isinstance(robot, bool) or not isinstance(robot, int) or robot < 0 or (
                    num_robots is not None and robot >= num_robots):
                limit = "" if num_robots is None else f" 0..{num_robots - 1}"
                raise TaskFileError(f"{here}: field 'robot': {robot!r} is not a robot id{limit}")
        tasks.append(Task(tuple(goals), robot, str(entry.get("id", f"{source}-{first_id + k}")), source))
    return tasks


def _task_cell(entry: dict, cell_field: str, xy_field: str, here: str, cell_of):
    if cell_field in entry:
        value = entry[cell_field]
        if (not isinstance(value, (list, tuple)) or len(value) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
            raise TaskFileError(f"{here}: field {cell_field!r}: expected [row, col] integers, "
                                f"got {value!r}")
        return int(value[0]), int(value[1])
    value = entry[xy_field]
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       and math.isfinite(v) for v in value)):
        raise TaskFileError(f"{here}: field {xy_field!r}: expected [x, y] finite numbers "
                            f"(metres), got {value!r}")
    if cell_of is None:
        raise TaskFileError(f"{here}: field {xy_field!r}: metres need the map's geometry")
    return tuple(int(v) for v in cell_of(float(value[0]), float(value[1])))


def yaml_error_text(where, exc) -> str:
    """One line for a YAML syntax error: `where:LINE:COLUMN: not valid YAML: the problem` (the
    parser's first line alone, "while parsing a flow sequence", names neither)."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    context = getattr(exc, "context", None)
    at = f"{where}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(where)
    return f"{at}: not valid YAML: {problem}" + (f" ({context})" if context else "")


def entry_lines(text: str) -> list[int]:
    """The 1-based line of each task of a task file's text ([] when it has no task list)."""
    import yaml

    try:
        root = yaml.compose(text)
    except yaml.YAMLError:
        return []
    if isinstance(root, yaml.MappingNode):
        root = next((v for k, v in root.value if getattr(k, "value", None) == "tasks"), None)
    if not isinstance(root, yaml.SequenceNode):
        return []
    return [item.start_mark.line + 1 for item in root.value]


def unreachable_problem(goals, grid, starts, robot: int | None = None) -> str:
    """Why a task's `goals` can never be reached by the robots standing on `starts` ("" when
    they can): a goal off the map or on an obstacle, a first goal in no region a robot (or
    `robot`) stands in (an enclosed cell), a later goal not reachable from the one before."""
    from scipy.ndimage import label

    grid = np.asarray(grid)
    h, w = grid.shape
    for k, (r, c) in enumerate(goals):
        name = _goal_name(goals, k)
        if not (0 <= r < h and 0 <= c < w):
            return f"{name} ({r}, {c}) is off the {h}x{w} map"
        if grid[r, c]:
            return f"{name} ({r}, {c}) is an obstacle"
    labels, _ = label(grid == 0)  # 4-connected regions of free cells
    starts = np.asarray(starts, dtype=np.int64).reshape(-1, 2)
    if robot is not None:
        starts = starts[[robot]]
    regions = {int(labels[r, c]) for r, c in starts}
    first = goals[0]
    if int(labels[first[0], first[1]]) not in regions:
        who = f"robot {robot}" if robot is not None else "any robot"
        name = "goal" if len(goals) == 1 else "pickup" if len(goals) == 2 else "goal 0"
        return (f"{name} ({first[0]}, {first[1]}) cannot be reached by {who}: it lies in a "
                f"region enclosed by obstacles")
    for k in range(1, len(goals)):
        a, b = goals[k - 1], goals[k]
        if labels[a[0], a[1]] != labels[b[0], b[1]]:
            return f"dropoff ({b[0]}, {b[1]}) cannot be reached from the pickup ({a[0]}, {a[1]})"
    return ""


INSTANCE_TASKS_REFUSED = (
    "the instance source keeps every robot on its instance goal for the whole run, so no robot "
    "is ever free to take a task: send one robot a goal instead (`mapf-fleet goal R --cell ROW "
    "COL` replaces its instance goal), or run with --task-source lifelong, tasks or external")


def task_problem(run, task: Task) -> str:
    """Why `run` (a `FleetRun`) cannot queue `task` ("" when it can): a robot it does not have,
    a goal off the map, on an obstacle or walled off; under the instance source, any task (its
    robots are never free: INSTANCE_TASKS_REFUSED). A goal another robot is headed for is no
    problem: the task waits until it moves on."""
    if not run.tasks.continuous:
        return INSTANCE_TASKS_REFUSED
    if task.robot is not None and not 0 <= task.robot < run.num_robots:
        return f"unknown robot {task.robot} (robots 0..{run.num_robots - 1})"
    for k, cell in enumerate(task.goals):
        problem = run.goal_problem(None, cell)
        if problem and not problem.startswith("robot "):  # a busy goal may free up later
            return f"{_goal_name(task.goals, k)}: {problem}"
    return unreachable_problem(task.goals, run.grid, run.positions, task.robot)


def batch_problems(run, tasks) -> dict[int, str]:
    """{index: why} for a request of several tasks, queued whole or not at all: each bad task's
    reason, and for each good one of a bad request that it was not queued either."""
    problems = {k: p for k, t in enumerate(tasks) if (p := task_problem(run, t))}
    if not problems:
        return {}
    bad = ", ".join(str(k) for k in problems)
    return {k: problems.get(k, f"not queued: task {bad} of this request "
                               f"{'was' if len(problems) == 1 else 'were'} rejected (a request "
                               f"is queued whole or not at all)") for k in range(len(tasks))}


def _goal_name(goals, k: int) -> str:
    return "goal" if len(goals) == 1 else ("pickup", "dropoff")[k] if len(goals) == 2 \
        else f"goal {k}"


def load_task_file(path: str, *, num_robots: int | None = None, cell_of=None, grid=None,
                   starts=None) -> list[Task]:
    """The tasks of a YAML file: a list of tasks, or a mapping with the list under `tasks`.
    With `grid` and `starts` (the robots' cells) every task is also checked reachable
    (`unreachable_problem`); errors name the file, the line and the task's index."""
    import yaml

    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise TaskFileError(f"{path}: cannot read the task file: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise TaskFileError(yaml_error_text(path, exc)) from None
    if isinstance(data, dict):
        if "tasks" not in data:
            raise TaskFileError(f"{path}: missing field 'tasks' (a list of tasks)")
        data = data["tasks"]
    lines = entry_lines(text)
    tasks = []
    for k, entry in enumerate(data if isinstance(data, list) else [data]):
        where = f"{path}:{lines[k]}" if k < len(lines) else str(path)
        if not isinstance(data, list):
            tasks += parse_tasks(data, str(path), num_robots=num_robots, cell_of=cell_of)
            break
        try:
            task, = parse_tasks([entry], where, num_robots=num_robots, cell_of=cell_of)
        except TaskFileError as exc:
            raise TaskFileError(str(exc).replace(f"{where}: task 0", f"{where}: task {k}",
                                                 1)) from None
        if "id" not in entry:
            task = Task(task.goals, task.robot, f"tasks-{k}", task.source)
        if grid is not None and starts is not None:
            problem = unreachable_problem(task.goals, grid, starts, task.robot)
            if problem:
                raise TaskFileError(f"{where}: task {k}: {problem}")
        tasks.append(task)
    if not tasks:
        raise TaskFileError(f"{path}: field 'tasks': the list is empty")
    return tasks
