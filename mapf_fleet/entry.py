"""One-line errors at the command entry points (`mapf-fleet` sub-commands, node mains).

The project's error types carry messages written for users (file, field, value):
`CheckpointError`, `MapFormatError`, `InstanceError`, `ProtocolError`, ... (all ValueError
subclasses), `FileNotFoundError` and other OSErrors, rclpy's parameter errors (a parameter of
the wrong type: `-p num_robots:=abc`) and rcl's refusal of its command line (an unreadable
`--params-file`). `run_main` prints such an error as one line `PROG: message` on stderr and
returns exit code 2; anything else is a bug and keeps its traceback. Set
MAPF_FLEET_TRACEBACK=1 to see the traceback of a user error too.
"""

from __future__ import annotations

import functools
import os
import re
import sys

EXIT_USER_ERROR = 2


def _ros_error_types() -> tuple:
    rclpy_exceptions = sys.modules.get("rclpy.exceptions")  # never import rclpy for this
    if rclpy_exceptions is None:
        return ()
    return (rclpy_exceptions.InvalidParameterException,
            rclpy_exceptions.InvalidParameterTypeException,
            rclpy_exceptions.InvalidParameterValueException,
            rclpy_exceptions.NameValidationException)


def is_user_error(exc: BaseException) -> bool:
    if isinstance(exc, (ValueError, OSError) + _ros_error_types()):
        return True
    # rclpy.init refusing its arguments (unreadable params file, bad remapping rule)
    return type(exc).__name__ == "RCLError" and "failed to initialize rcl" in str(exc)


def error_line(exc: BaseException) -> str:
    """The message of a user error as one line (rcl's source locations dropped)."""
    text = str(exc).strip() or type(exc).__name__
    if type(exc).__name__ == "RCLError":
        text = re.sub(r",? at /\S+:\d+", "", text).replace("failed to initialize rcl: ", "")
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


def run_main(prog: str, func, argv=None) -> int:
    """`func(argv)`, with a user error printed as `prog: message` and exit code 2."""
    try:
        return int(func(argv) or 0)
    except Exception as exc:
        if not is_user_error(exc) or os.environ.get("MAPF_FLEET_TRACEBACK"):
            raise
        print(f"{prog}: {error_line(exc)}", file=sys.stderr, flush=True)
        return EXIT_USER_ERROR


def one_line_errors(prog: str):
    """Decorator for a `main(argv=None) -> int`: see `run_main`."""

    def wrap(func):
        @functools.wraps(func)
        def main(argv=None):
            return run_main(prog, func, argv)

        return main

    return wrap
