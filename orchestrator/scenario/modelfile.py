"""A scene's model file (``scene: {model: robot.xml}``), looked at before the engine reads it.

The engine reads a file it is given to its end, follows its ``<include>`` elements, expands its
``<replicate>`` elements and loads its assets, all in C, with no limit: a device (``/dev/zero``) fills
the memory, a FIFO hangs, and three nested replicates of 1,000 make a billion bodies. So the file and
what it names are read here first, within limits, and the bodies the engine would make are counted:

- every file (the model, each include, each asset a ``file=`` names) is a regular file: no device, no
  FIFO, no folder (a link is followed to what it names);
- a model or include file holds at most `limits.MAX_MODEL_BYTES`, read with that bound; all of them
  together too, and includes nest at most `MAX_INCLUDE_DEPTH` deep; an asset holds at most
  `limits.MAX_ASSET_BYTES`;
- the XML declares no DOCTYPE (no entities to expand);
- bodies are counted as the engine makes them: each ``<body>`` (a URDF's ``<link>``) times the counts
  of the replicates around it, a ``composite``'s or ``flexcomp``'s ``count`` elements, the bodies of
  a sub-model at each ``<attach>`` (all of them: an upper bound when a subtree is attached); the count
  stops as soon as it passes `limits.MAX_BODIES`.
"""

from __future__ import annotations

import math
import os
import stat
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

from . import limits

MAX_INCLUDE_DEPTH = 10
"""How deeply ``<include>`` elements (and attached sub-models) may nest."""
_ASSET_DIRS = {"mesh": "meshdir", "skin": "meshdir", "texture": "texturedir", "hfield": "texturedir"}


class ModelFileError(Exception):
    """A model file refused before the engine reads it; the message says which file and why."""


@dataclass
class _Scan:
    bodies: int = 0
    xml_bytes: int = 0
    dirs: dict[str, str] = field(default_factory=dict)
    """The ``<compiler>``'s asset folders (meshdir, texturedir, assetdir), as written."""
    models: dict[str, int] = field(default_factory=dict)
    """The bodies of each sub-model (``<asset><model name file>``), counted again at each ``<attach>``."""


def regular_file(path: str, what: str, limit: int) -> int:
    """The size of ``path`` when it is a regular file of at most ``limit`` bytes; else a `ModelFileError`."""
    try:
        info = os.stat(path)
    except OSError as exc:
        raise ModelFileError(f"{what} {path!r} cannot be read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(info.st_mode):
        kind = ("a folder" if stat.S_ISDIR(info.st_mode) else "a FIFO" if stat.S_ISFIFO(info.st_mode)
                else "a device" if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode) else "a socket")
        raise ModelFileError(f"{what} {path!r} is {kind}, not a regular file")
    if info.st_size > limit:
        raise ModelFileError(f"{what} {path!r} holds {info.st_size} bytes, more than {limit} ({_name(limit)})")
    return info.st_size


def read_bounded(path: str, what: str, limit: int) -> bytes:
    """The bytes of the regular file ``path``, read with the bound ``limit`` (it may grow meanwhile)."""
    regular_file(path, what, limit)
    with open(path, "rb") as fh:
        raw = fh.read(limit + 1)
    if len(raw) > limit:
        raise ModelFileError(f"{what} {path!r} holds more than {limit} bytes ({_name(limit)})")
    return raw


def count_bodies(path: str) -> int:
    """How many bodies the engine would make of the model file ``path`` (see the module docstring): at
    most `limits.MAX_BODIES` + 1 (a count that passes the limit stops there). Raises `ModelFileError`."""
    scan = _Scan()
    _file(path, scan, 1, 0)
    return scan.bodies


def _file(path: str, scan: _Scan, multiplier: int, depth: int, folder: str | None = None) -> None:
    """Count the bodies of the file ``path``; its includes and assets are found from ``folder`` (the
    top model's folder, as MuJoCo looks for them; a sub-model's own for its own), an include also
    beside the file that includes it (MuJoCo looks there too)."""
    if depth > MAX_INCLUDE_DEPTH:
        raise ModelFileError(f"{path!r}: includes nest deeper than {MAX_INCLUDE_DEPTH} (MAX_INCLUDE_DEPTH)")
    raw = read_bounded(path, "model file" if depth == 0 else "included file", limits.MAX_MODEL_BYTES)
    scan.xml_bytes += len(raw)
    if scan.xml_bytes > limits.MAX_MODEL_BYTES:
        raise ModelFileError(f"{path!r}: the model and its includes hold more than {limits.MAX_MODEL_BYTES} bytes "
                             "(MAX_MODEL_BYTES)")
    if b"<!DOCTYPE" in raw or b"<!ENTITY" in raw:
        raise ModelFileError(f"{path!r} declares a DOCTYPE or entities, which a model file has no use for")
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as exc:
        raise ModelFileError(f"{path!r} is not well-formed XML: {exc}") from None
    here = os.path.dirname(os.path.abspath(path))
    if root.tag == "robot":  # URDF: a link per body, no includes
        _add(scan, multiplier * sum(1 for _ in root.iter("link")))
        return
    _element(root, (folder or here, here), scan, multiplier, depth)


def _element(node: ET.Element, folders: tuple[str, str], scan: _Scan, multiplier: int, depth: int) -> None:
    """Count the bodies under ``node``; ``folders``: the top model's folder and the current file's."""
    folder, here = folders
    for child in node:
        tag = child.tag if isinstance(child.tag, str) else ""
        inner = multiplier
        if tag == "compiler":
            scan.dirs.update({k: v for k, v in child.attrib.items() if k in ("meshdir", "texturedir", "assetdir")})
        elif tag == "include":
            first = os.path.join(folder, child.get("file", ""))
            found = first if os.path.lexists(first) else os.path.join(here, child.get("file", ""))
            _file(found, scan, multiplier, depth + 1, folder)
            continue
        elif tag == "body":
            _add(scan, multiplier)
        elif tag == "replicate":
            inner = multiplier * _whole(child.get("count", "1"), "replicate count")
        elif tag in ("composite", "flexcomp"):
            counts = [_whole(c, f"{tag} count") for c in (child.get("count") or "1").split()]
            _add(scan, multiplier * math.prod(counts))
        elif tag == "model" and child.get("file"):  # a sub-model: its bodies count at each <attach>
            sub = _Scan(xml_bytes=scan.xml_bytes)
            _file(_asset_path(folder, scan, "model", child.get("file", "")), sub, 1, depth + 1)
            scan.models[child.get("name", "")], scan.xml_bytes = sub.bodies, sub.xml_bytes
            continue
        elif tag == "attach":  # (all the sub-model's bodies, whichever subtree it attaches: at most that)
            _add(scan, multiplier * scan.models.get(child.get("model", ""), 0))
        if child.get("file") and tag in _ASSET_DIRS:
            regular_file(_asset_path(folder, scan, tag, child.get("file", "")), f"{tag} file", limits.MAX_ASSET_BYTES)
        _element(child, folders, scan, inner, depth)


def _asset_path(folder: str, scan: _Scan, tag: str, file: str) -> str:
    """Where the engine looks for an asset: the compiler's folder for its kind (else ``assetdir``), from
    the model's folder; the model's folder itself when the file is not there."""
    sub = scan.dirs.get(_ASSET_DIRS.get(tag, ""), scan.dirs.get("assetdir", ""))
    first = os.path.join(folder, sub, file)
    return first if os.path.lexists(first) or not sub else os.path.join(folder, file)


def _add(scan: _Scan, bodies: int) -> None:
    scan.bodies += bodies
    if scan.bodies > limits.MAX_BODIES:  # stop at once: no need to count a billion
        raise _TooManyBodiesError(scan.bodies)


class _TooManyBodiesError(ModelFileError):
    def __init__(self, bodies: int):
        super().__init__(f"at least {bodies} bodies, its includes and replicates counted: a scene has at most "
                         f"{limits.MAX_BODIES} (MAX_BODIES)")
        self.bodies = bodies


def _whole(text: str, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise ModelFileError(f"{what} {text!r} is not a whole number") from None
    if value < 0:
        raise ModelFileError(f"{what} {value} is negative")
    return value


def _name(limit: int) -> str:
    return "MAX_MODEL_BYTES" if limit == limits.MAX_MODEL_BYTES else "MAX_ASSET_BYTES"
