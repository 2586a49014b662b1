"""An FMU's zip archive, opened and extracted within limits.

An FMU is a zip that dynabrain opens (to read its model description) and extracts (to load its
binary). A zip says how large each member is once expanded, and a few MB of zeros expand to GB (a
"zip bomb"); a member's name may climb out of the folder (``../../.bashrc``, ``/etc/...``: a "zip
slip"). So before anything is read, `check_archive` refuses:

- more than `MAX_MEMBERS` members, or more than `MAX_FMU_BYTES` in all once expanded;
- a member larger than 1 MiB that expands more than `MAX_RATIO` times its compressed size (binaries
  and model descriptions expand 2 to 20 times; a bomb about 1,000);
- a name that is absolute, holds ``..``, a backslash or a drive letter.

`extract` then writes each member inside the folder, no more bytes than the archive declared for it
(Python's zip reader stops at the declared size and checks the CRC).
"""

from __future__ import annotations

import os
import shutil
import stat
import zipfile
from pathlib import Path

from .errors import FMUError

MAX_FMU_BYTES = 1024 * 1024 * 1024
"""The most an FMU may expand to, all members together: 1 GiB."""
MAX_RATIO = 100
"""The most a member above `_RATIO_FROM` bytes may expand, relative to its compressed size."""
MAX_MEMBERS = 20_000
"""The most members (files and folders) an FMU archive may hold."""
_RATIO_FROM = 1024 * 1024


def check_archive(zf: zipfile.ZipFile, label: str) -> None:
    """Raise `FMUError` naming ``label`` and the member at fault when ``zf`` passes a limit (see the
    module docstring). Reads the archive's directory only."""
    members = zf.infolist()
    if len(members) > MAX_MEMBERS:
        raise FMUError(f"{label}: the archive holds {len(members)} members, more than {MAX_MEMBERS} (MAX_MEMBERS)")
    total = 0
    for info in members:
        _check_name(info.filename, label)
        total += info.file_size
        if total > MAX_FMU_BYTES:
            raise FMUError(f"{label}: the archive expands to more than {MAX_FMU_BYTES} bytes (MAX_FMU_BYTES); "
                           f"{info.filename!r} passes the limit")
        if info.file_size > _RATIO_FROM and info.file_size > MAX_RATIO * max(info.compress_size, 1):
            raise FMUError(f"{label}: {info.filename!r} expands {info.file_size // max(info.compress_size, 1)} times "
                           f"(from {info.compress_size} to {info.file_size} bytes), more than {MAX_RATIO} (MAX_RATIO): "
                           "a zip bomb, not an FMU")


def not_regular(path: str | Path, label: str) -> None:
    """Raise `FMUError` when ``path`` exists and is neither a regular file nor a folder (an FMU's source):
    a FIFO would hang the zip reader, a device would feed it without end. A link is followed."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return  # (missing: the caller says so)
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        kind = "a FIFO" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else \
            "a socket"
        raise FMUError(f"{label}: {os.fspath(path)!r} is {kind}, not a file")


def _check_name(name: str, label: str) -> None:
    parts = name.split("/")
    if "\\" in name or ":" in name or name.startswith("/") or ".." in parts or "\0" in name:
        raise FMUError(f"{label}: the archive member {name!r} would be written outside the FMU's folder (an "
                       "absolute path, '..', a backslash or a drive letter)")


def open_checked(path: str | Path, label: str) -> zipfile.ZipFile:
    """``path`` opened as a zip whose directory `check_archive` accepts."""
    zf = zipfile.ZipFile(path)
    try:
        check_archive(zf, label)
    except BaseException:
        zf.close()
        raise
    return zf


def extract(path: str | Path, folder: str, label: str) -> None:
    """Extract the FMU at ``path`` into ``folder`` within the limits (see the module docstring)."""
    root = os.path.realpath(folder)
    try:
        with open_checked(path, label) as zf:
            for info in zf.infolist():
                target = os.path.realpath(os.path.join(root, info.filename))
                if os.path.commonpath([root, target]) != root:
                    raise FMUError(f"{label}: the archive member {info.filename!r} would be written outside the "
                                   "FMU's folder")
                if info.is_dir():
                    os.makedirs(target, exist_ok=True)
                    continue
                os.makedirs(os.path.dirname(target), exist_ok=True)
                with zf.open(info) as src, open(target, "wb") as dst:
                    shutil.copyfileobj(src, dst, 1024 * 1024)
    except FMUError:
        raise
    except (OSError, zipfile.BadZipFile, EOFError, ValueError) as exc:
        raise FMUError(f"{label}: cannot extract: {type(exc).__name__}: {exc}") from None
