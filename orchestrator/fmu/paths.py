"""Where FMUs are found and where built ones are kept.

Built FMUs and the compiled step helper live in a cache outside the working tree:
``$DYNABRAIN_CACHE``, else ``$XDG_CACHE_HOME/dynabrain``, else ``~/.cache/dynabrain``.
"""

from __future__ import annotations

import os
from pathlib import Path

import fmpy

from .errors import FMUError

FMI2_PLATFORM = fmpy.platform  # "linux64"
FMI3_PLATFORM = fmpy.platform_tuple  # "x86_64-linux"
SHARED_LIB_EXT = fmpy.sharedLibraryExtension


def cache_dir() -> Path:
    """The dynabrain cache folder (created on first use)."""
    root = os.environ.get("DYNABRAIN_CACHE")
    if root:
        path = Path(root)
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        path = (Path(xdg) if xdg else Path.home() / ".cache") / "dynabrain"
    path.mkdir(parents=True, exist_ok=True)
    return path


def fmi_headers_dir() -> Path:
    """The FMI 2.0 / 3.0 C headers shipped inside fmpy."""
    return Path(fmpy.__file__).parent / "c-code"


def glue_dir() -> Path:
    """The C glue every dynabrain FMU is built with (``csrc/`` beside this file)."""
    return Path(__file__).parent / "csrc"


def binary_dir(version: int) -> str:
    """The folder inside an FMU that holds this machine's binary."""
    return f"binaries/{FMI3_PLATFORM if version == 3 else FMI2_PLATFORM}"  # FMI 1.0 and 2.0 name it alike


def split_version(ref: str) -> tuple[str, int | None]:
    """``fmus/servo@fmi3`` -> (``fmus/servo``, 3); no suffix -> (ref, None)."""
    path, sep, suffix = ref.rpartition("@")
    if not sep:
        return ref, None
    if suffix not in ("fmi1", "fmi2", "fmi3"):
        raise FMUError(f"FMU reference {ref!r}: the suffix after @ is fmi1, fmi2 or fmi3, not {suffix!r}")
    return path, int(suffix[-1])


def resolve(ref: str, base_dir: str | os.PathLike[str]) -> Path:
    """The FMU file or source folder ``ref`` names: as written when absolute; else relative to
    ``base_dir`` or to the closest of its parent folders where it exists (so a scenario in
    ``scenarios/`` can name ``fmus/servo``)."""
    path = Path(ref).expanduser()
    if path.is_absolute():
        if not path.exists():
            raise FMUError(f"FMU {ref!r} not found")
        return path
    base = Path(base_dir).resolve()
    tried = []
    for folder in (base, *base.parents):
        candidate = folder / path
        if candidate.exists():
            return candidate
        tried.append(str(folder))
    raise FMUError(f"FMU {ref!r} not found (looked in {tried[0]} and its parent folders)")
