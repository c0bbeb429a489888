"""File writing shared by checkpoints, training state, datasets, caches and reports: the
project's one atomic writer."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

# Every temporary file of `atomic_write` is named ".<name>.tmp-<random>" beside its target, so a
# folder's leftovers of a killed writer are `folder.glob(f"*{TMP_MARK}*")`.
TMP_MARK = ".tmp-"


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None] | bytes) -> Path:
    """Write `path` through `write(handle)` (or write the bytes `write`) so that a reader (or a
    run resumed after kill -9) sees either the old file or the complete new one: temporary file
    in the same directory, fsync, then os.replace."""
    path = Path(path)
    if isinstance(write, (bytes, bytearray, memoryview)):
        data = write
        write = lambda handle: handle.write(data)  # noqa: E731
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}{TMP_MARK}", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
