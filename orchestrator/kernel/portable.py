"""Portable world state: a world's whole state as bytes that another World, built the same way in
another process or on another host, takes back bit for bit (`World.export_state`, `World.import_state`).

Layout (format 1), all integers little-endian::

    magic      16 bytes   b"DYNABRAIN-STATE\\n"
    length      4 bytes   unsigned, the length of the header that follows
    header     JSON, UTF-8
        format      1
        dynabrain   the exporting package's version (a different version is refused)
        world       the world's name;   step_ns: its base step
        tick        the tick the state is at
        modules     one entry per module present, in the structure's order:
                    {name, class ("package.module:Class"), signature, period_ns, phase, spec}
                    ``signature`` hashes the module's class and its ports (names, shapes, units): a core
                    built from another scene has other ports, so its state is refused
                    ``spec`` is the scenario syntax that makes the module again (`module_spec`)
        connections [[src, dst, delay], ...]
        bus         the bus's size in float64 values
    payload    a pickle (protocol 5) of ``(bus, states, params)``: the bus as a float64 array, each
               module's ``get_state()`` value, each module's parameter dict, in the modules' order.

The payload is read by a restricted unpickler: it may rebuild plain values (numbers, strings, bytes,
tuples, lists, dicts), numpy arrays, NamedTuples and dataclasses of dynabrain's own modules that pickle
the default way (making one runs none of their code), and the classes registered with `state_type`;
nothing else, so bytes from elsewhere cannot run code. A module whose state holds another type is refused when the
state is imported, naming the module and the type. Module states are otherwise opaque here: each
module's `get_state` and `set_state` define them.
"""

from __future__ import annotations

import copyreg
import dataclasses
import functools
import hashlib
import io
import json
import pickle
import struct
import sys
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from typing import Any, TypeVar

import numpy as np

from .errors import DynabrainError

MAGIC = b"DYNABRAIN-STATE\n"
FORMAT = 1
_LENGTH = struct.Struct("<I")

T = TypeVar("T")

_STATE_TYPES: dict[tuple[str, str], Any] = {}


class StateFormatError(DynabrainError):
    """Bytes that are not a portable world state, or a state this world cannot take."""


def state_type(cls: T) -> T:
    """Register a class whose instances may appear in a module's state (a NamedTuple, a frozen
    dataclass): the portable state's reader rebuilds only registered classes. Use as a decorator."""
    _STATE_TYPES[(cls.__module__, cls.__qualname__)] = cls  # type: ignore[attr-defined]
    return cls


def register_state_value(module: str, name: str, value: Any) -> None:
    """Register a named object (a sentinel such as ``UNRESTORABLE``) that a state may refer to."""
    _STATE_TYPES[(module, name)] = value


# numpy's own reconstruction of arrays, scalars and dtypes (under its module names of 1.x and 2.x)
_NP = getattr(np, "_core", None) or np.core
for _prefix in ("numpy.core", "numpy._core"):
    _STATE_TYPES[(f"{_prefix}.multiarray", "_reconstruct")] = _NP.multiarray._reconstruct
    _STATE_TYPES[(f"{_prefix}.multiarray", "scalar")] = _NP.multiarray.scalar
    _STATE_TYPES[(f"{_prefix}.numeric", "_frombuffer")] = _NP.numeric._frombuffer
_STATE_TYPES[("numpy", "ndarray")] = np.ndarray
_STATE_TYPES[("numpy", "dtype")] = np.dtype
for _name in dir(np.dtypes):
    if _name.endswith("DType") and not _name.startswith(("Object", "Void", "StringDType")):
        _STATE_TYPES[("numpy.dtypes", _name)] = getattr(np.dtypes, _name)
_STATE_TYPES[("builtins", "frozenset")] = frozenset
_STATE_TYPES[("builtins", "set")] = set
_STATE_TYPES[("builtins", "complex")] = complex
_STATE_TYPES[("builtins", "slice")] = slice
_STATE_TYPES[("collections", "OrderedDict")] = __import__("collections").OrderedDict


_STATE_TYPES[("copyreg", "__newobj__")] = copyreg.__newobj__  # how a dataclass instance is made (no __init__)
_STATE_TYPES[("copyreg", "_reconstructor")] = copyreg._reconstructor


def _plain_data_class(obj: Any) -> bool:
    """A NamedTuple or a dataclass that pickles the default way: making one runs no code of its own."""
    if not isinstance(obj, type):
        return False
    named_tuple = issubclass(obj, tuple) and hasattr(obj, "_fields")  # its __new__ is namedtuple's own
    if not (named_tuple or dataclasses.is_dataclass(obj)):
        return False
    hooks = ["__reduce__", "__reduce_ex__", "__setstate__"] + ([] if named_tuple else ["__new__"])
    return all(getattr(obj, hook, None) is getattr(object, hook, None) for hook in hooks)


class _Unrestorable:
    def __repr__(self) -> str:
        return "UNRESTORABLE"

    def __reduce__(self) -> str:
        return "UNRESTORABLE"  # pickled and copied as this very object


UNRESTORABLE = _Unrestorable()
"""What history holds for the state of a module that cannot roll back (`structure` names it too)."""
_UNRESTORABLE_HOMES = ("dynabrain.orchestrator.kernel.portable", "dynabrain.orchestrator.kernel.structure")
"""Where a pickled UNRESTORABLE may say it lives (its home before it moved here, too)."""


class _Reader(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        found = _STATE_TYPES.get((module, name))
        if found is not None:
            return found
        if module in _UNRESTORABLE_HOMES and name == "UNRESTORABLE":
            return UNRESTORABLE
        loaded = sys.modules.get(module) if module.startswith("dynabrain.") else None  # never imports
        obj = getattr(loaded, name, None) if "." not in name else None
        if loaded is not None and _plain_data_class(obj):
            return obj
        raise StateFormatError(f"the state holds a {module}.{name}, which is not a state type (a plain value, a "
                               "numpy array, a NamedTuple or dataclass of dynabrain's, or a class registered with "
                               "dynabrain.orchestrator.kernel.portable.state_type)")


def loads(data: bytes) -> Any:
    """Unpickle ``data`` with the restricted reader."""
    return _Reader(io.BytesIO(data)).load()


@dataclass(frozen=True)
class ModuleEntry:
    """One module of a portable state's header."""

    name: str
    cls: str
    signature: str
    period_ns: int
    phase: int
    spec: dict[str, Any]


@dataclass(frozen=True)
class PortableState:
    """A portable state, read: the header's fields and the payload's values."""

    world: str
    step_ns: int
    tick: int
    modules: tuple[ModuleEntry, ...]
    connections: tuple[tuple[str, str, bool], ...]
    bus: np.ndarray
    states: tuple[Any, ...]
    params: tuple[dict[str, Any], ...]


@functools.cache
def version() -> str:
    """This dynabrain's version (a state from another version is refused); read once."""
    try:
        return metadata.version("dynabrain")
    except metadata.PackageNotFoundError:
        return "unknown"


def signature(module: Any, ports: Any) -> str:
    """A short hash of a module's class and its ``ports``: two modules with the same signature lay out
    the same state (a core's ports name every body, joint and sensor of its scene). The World keeps
    each module's (`World._signature_of`): a core has hundreds of ports."""
    cls = type(module)
    ports = [(p.name, tuple(p.shape), p.unit) for p in ports]
    text = json.dumps([f"{cls.__module__}:{cls.__qualname__}", ports], separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def encode(header: dict[str, Any], bus: np.ndarray, states: tuple, params: tuple,
           owner: Callable[[int], str]) -> bytes:
    """The bytes of a state; ``owner(i)`` names the module of ``states[i]`` for errors."""
    try:
        payload = pickle.dumps((bus, states, params), protocol=5)
    except Exception as exc:  # which module? pickle each state alone to say
        for i, value in enumerate(states):
            try:
                pickle.dumps(value, protocol=5)
            except Exception as inner:
                raise DynabrainError(f"export_state: the state of module {owner(i)!r} cannot be serialized: "
                                     f"{type(inner).__name__}: {inner}") from None
        raise DynabrainError(f"export_state: the state cannot be serialized: {type(exc).__name__}: {exc}") from None
    head = json.dumps({"format": FORMAT, "dynabrain": version(), **header}, separators=(",", ":")).encode()
    return b"".join((MAGIC, _LENGTH.pack(len(head)), head, payload))


def decode(data: bytes) -> PortableState:
    """Read the bytes of a state; `StateFormatError` says what is wrong with them."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise StateFormatError(f"import_state takes the bytes of export_state, got {type(data).__name__}")
    data = bytes(data)
    if not data.startswith(MAGIC) or len(data) < len(MAGIC) + _LENGTH.size:
        raise StateFormatError("these bytes are not a dynabrain world state (no DYNABRAIN-STATE header)")
    at = len(MAGIC) + _LENGTH.size
    (length,) = _LENGTH.unpack_from(data, len(MAGIC))
    try:
        head = json.loads(data[at:at + length].decode())
    except (UnicodeDecodeError, ValueError):
        raise StateFormatError("the world state's header is damaged (not JSON)") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise StateFormatError(f"world state format {head.get('format') if isinstance(head, dict) else '?'} "
                               f"is not the format this dynabrain reads ({FORMAT})")
    if head.get("dynabrain") != version():
        raise StateFormatError(f"the world state was exported by dynabrain {head.get('dynabrain')}, this is "
                               f"{version()}: states cross only between equal versions")
    try:
        modules = tuple(ModuleEntry(m["name"], m["class"], m["signature"], int(m["period_ns"]), int(m["phase"]),
                                    dict(m["spec"])) for m in head["modules"])
        connections = tuple((str(s), str(d), bool(x)) for s, d, x in head["connections"])
        world, step_ns, tick, size = str(head["world"]), int(head["step_ns"]), int(head["tick"]), int(head["bus"])
    except (KeyError, TypeError, ValueError):
        raise StateFormatError("the world state's header is damaged (fields missing or of the wrong type)") from None
    try:
        bus, states, params = loads(data[at + length:])
    except StateFormatError:
        raise
    except Exception as exc:
        raise StateFormatError(f"the world state's payload is damaged: {type(exc).__name__}: {exc}") from None
    if (not isinstance(bus, np.ndarray) or bus.dtype != np.float64 or bus.shape != (size,)
            or len(states) != len(modules) or len(params) != len(modules)):
        raise StateFormatError("the world state's payload does not match its header")
    return PortableState(world, step_ns, tick, modules, connections, bus, tuple(states), tuple(params))
