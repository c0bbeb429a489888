"""Which code produced a file: recorded in checkpoints, evaluation JSON and model cards."""

from __future__ import annotations

import functools
import os
import subprocess
from pathlib import Path
from typing import Any

import mapf_fleet


def code_version() -> dict[str, Any]:
    """Package version and the git commit of the source tree when it is a git checkout.

    Read once per process: a long run (training for hours) records the commit it started from,
    not one checked out while it ran (the loaded code is the one of its start)."""
    return dict(_code_version())


@functools.cache
def _code_version() -> dict[str, Any]:
    commit = None
    try:
        # GIT_OPTIONAL_LOCKS=0: read only, never touch the index. (git is no ROS process;
        # ROS_AUTOMATIC_DISCOVERY_RANGE does not concern it.)
        result = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(mapf_fleet.__file__).resolve().parent,
            capture_output=True, text=True, timeout=5,
            env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"},
        )
        if result.returncode == 0:
            commit = result.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"package": mapf_fleet.__version__, "git_commit": commit}
