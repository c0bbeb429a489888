"""Errors raised on bad input: they name the file/line or the agent/cell at fault, so a user never
has to read a numpy traceback to find out what is wrong."""

from __future__ import annotations

from os import PathLike


class MapFormatError(ValueError):
    """A malformed map, scenario or test-set file.

    `str(err)` reads ``<file>:<line>: <problem>`` (line omitted when the problem is not tied to a
    line, e.g. a missing array in an .npz file).
    """

    def __init__(self, file: str | PathLike, line: int | None, problem: str):
        self.file = str(file)
        self.line = line
        self.problem = problem
        where = self.file if line is None else f"{self.file}:{line}"
        super().__init__(f"{where}: {problem}")


class InstanceError(ValueError):
    """An invalid MAPF instance; names the agent and the cell when the problem concerns one."""

    def __init__(self, problem: str, agent: int | None = None, cell: tuple[int, int] | None = None):
        self.problem = problem
        self.agent = agent
        self.cell = None if cell is None else (int(cell[0]), int(cell[1]))
        parts = []
        if agent is not None:
            parts.append(f"agent {agent}")
        if self.cell is not None:
            parts.append(f"cell (row={self.cell[0]}, col={self.cell[1]})")
        prefix = ", ".join(parts)
        super().__init__(f"{prefix}: {problem}" if prefix else problem)
