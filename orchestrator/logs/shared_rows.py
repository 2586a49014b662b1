"""Rows of the bus in shared memory, for the child writer of a log (`logs.sinks.ProcessSink`): each block of
rows is a file in ``/dev/shm`` (or the temporary folder when that is missing or full), mapped by both
processes; a file's name is removed as soon as the child has mapped it, and files of processes killed
before that are removed by the next log started (`remove_stale_rows`).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import tempfile

import numpy as np

from ..kernel.errors import DynabrainError
from .messages import (
    Shared,
)


# -- shared rows ------------------------------------------------------------------------------------------
class SharedRows:
    """A float64 array in a file of shared memory (``/dev/shm`` where there is one), mapped here and, by
    its path, in the child writer."""

    def __init__(self, shape: tuple[int, ...]):
        size = max(8, 8 * int(np.prod(shape)))
        error: OSError | None = None
        for folder in _row_folders():
            try:
                self._map, self.path = _reserve(folder, size)
                break
            except OSError as exc:
                error = exc
        else:
            raise DynabrainError(f"no memory to share rows with the log writer ({size} bytes): {error}")
        self.array = np.frombuffer(self._map, dtype=np.float64, count=int(np.prod(shape))).reshape(shape)

    def release(self) -> None:
        self.array = None  # type: ignore[assignment]
        with contextlib.suppress(BufferError, ValueError):
            self._map.close()
        with contextlib.suppress(OSError):
            os.unlink(self.path)


def _reserve(folder: str, size: int) -> tuple[mmap.mmap, str]:
    """A new file of ``size`` bytes in ``folder``, its memory reserved (a full tmpfs, such as a
    container's small /dev/shm, refuses here rather than killing the simulation with SIGBUS when a
    row is written), mapped."""
    fd, path = tempfile.mkstemp(prefix=f"{_PREFIX}{os.getpid()}-", dir=folder)
    try:
        if hasattr(os, "posix_fallocate"):
            os.posix_fallocate(fd, 0, size)
        else:
            os.ftruncate(fd, size)
        # mapped with its pages (MAP_POPULATE, where there is one): the rows written later fault no page in
        flags = mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0)
        return mmap.mmap(fd, size, flags=flags), path
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(path)
        raise
    finally:
        os.close(fd)


def mapped(shared: Shared, maps: dict[str, tuple[mmap.mmap, np.ndarray]]) -> np.ndarray:
    """The child's view of a shared array (mapped once per path)."""
    path, shape = shared
    hit = maps.get(path)
    if hit is None:
        with open(path, "r+b") as fh:  # its pages mapped now (they exist: the parent reserved them), not
            mm = mmap.mmap(fh.fileno(), 0, flags=mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0))  # row by row
        with contextlib.suppress(OSError):
            os.unlink(path)  # both processes have it mapped now: the name is no longer needed
        hit = maps[path] = (mm, np.frombuffer(mm, dtype=np.float64, count=int(np.prod(shape))).reshape(shape))
    return hit[1]


def remove_stale_rows() -> None:
    """Remove shared-row files left by processes that no longer run (both killed before the child
    mapped a block); their names carry the simulation's process id."""
    for folder in _row_folders():
        with contextlib.suppress(OSError):
            for name in os.listdir(folder):
                if not name.startswith(_PREFIX):
                    continue
                pid = name[len(_PREFIX):].split("-", 1)[0]
                if pid.isdigit() and not _alive(int(pid)):
                    with contextlib.suppress(OSError):
                        os.unlink(os.path.join(folder, name))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _row_folders() -> list[str]:
    """Where shared rows go: ``/dev/shm`` (memory) where there is one, else (or when it is full) the
    temporary folder."""
    shm = ["/dev/shm"] if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else []
    return list(dict.fromkeys([*shm, tempfile.gettempdir()]))


_PREFIX = "dynabrain-log-"
