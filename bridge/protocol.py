"""The bridge's wire format, JSON part: key expressions, command envelopes, the arguments of every call,
replies, errors and brain inputs. `PROTOCOL.md` describes it; `protocol.schema.json` is generated from
these models (``python -m dynabrain.bridge.schema``) and every incoming JSON message is validated by
them. Binary frames (state, robot) are in `frames`.

Every model refuses unknown fields and wrong types (strict: ``"1"`` is not an int); a payload larger
than its limit is refused before it is parsed.
"""

from __future__ import annotations

import json
import math
import re
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model

from dynabrain.orchestrator.kernel.errors import DynabrainError

VERSION = 1
PREFIX = "dynabrain"
MAX_COMMAND_BYTES = 256 * 1024
"""Largest command payload accepted (an ``add_module`` with its parameters fits many times over)."""
MAX_INPUT_BYTES = 64 * 1024
"""Largest brain input (``in/set``, ``in/motion``) accepted."""
MAX_TICKS = 1_000_000
MAX_NAMES = 10_000
WORLD_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")
JSON_ENCODING = "application/json"
FRAME_ENCODING = "application/octet-stream;dynabrain.frame.v1"


class ProtocolError(DynabrainError):
    """A message that does not follow the protocol: ``kind`` is ``bad_request`` (malformed, oversized,
    wrong types) or ``unknown_call``."""

    def __init__(self, message: str, kind: str = "bad_request"):
        super().__init__(message)
        self.kind = kind


# -- key expressions ---------------------------------------------------------------------------------------
def check_world_name(name: str) -> str:
    if not isinstance(name, str) or not WORLD_NAME.match(name):
        raise ProtocolError(f"world name {name!r} is not valid: 1 to 64 of letters, digits, '_', '-', '.'")
    return name


def key(world: str, *parts: str) -> str:
    """``dynabrain/<world>/<parts...>``."""
    return "/".join((PREFIX, world, *parts))


def call_key(world: str, call: str) -> str:
    return key(world, "call", call)


def robot_key(world: str, robot: str, *parts: str) -> str:
    return key(world, "robot", robot, *parts)


# -- commands ----------------------------------------------------------------------------------------------
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


Name = Annotated[str, Field(min_length=1, max_length=256)]
Names = Annotated[list[Name], Field(min_length=1, max_length=MAX_NAMES)]
Number = float | int
Value = Number | bool | str | list[Any]
"""A value to set: a number, a boolean, a string, or (nested) lists of numbers."""


class Envelope(_Strict):
    """What every command carries: the protocol version, the calling brain and its arguments."""

    v: Literal[1] = 1
    brain: Annotated[str, Field(min_length=1, max_length=128)] | None = None
    """The caller's brain id (its liveliness token is ``dynabrain/<world>/brain/<id>``)."""
    instance: int | None = None
    """The server instance the brain believes it talks to; a restarted server refuses the call."""
    args: dict[str, Any] = {}


class NoArgs(_Strict):
    pass


class TickArgs(_Strict):
    n: Annotated[int, Field(ge=1, le=MAX_TICKS)] = 1
    view: Annotated[int, Field(ge=0)] | None = None
    """Reply with a state frame of this view (see ``view``) instead of JSON."""


class BacktickArgs(_Strict):
    n: Annotated[int, Field(ge=0, le=MAX_TICKS)] = 1


class StartArgs(_Strict):
    realtime: bool | Annotated[float, Field(gt=0, le=1000)] = False
    """False: as fast as possible; True: real time; a number: a speed factor."""
    until: Annotated[float, Field(ge=0)] | None = None
    """Stop by itself at this simulated time (s)."""


class ObjectsArgs(_Strict):
    objects: Names


class MakeJointArgs(_Strict):
    a: Name
    b: Name
    name: Name | None = None


class NameArgs(_Strict):
    name: Name


class PlaceArgs(_Strict):
    body: Name
    pos: Annotated[list[Number], Field(min_length=3, max_length=3)]
    quat: Annotated[list[Number], Field(min_length=4, max_length=4)] | None = None


class SetArgs(_Strict):
    name: Name
    value: Value


class ModuleSpec(_Strict):
    """A module in the scenario's module syntax (``python:`` or ``fmu:``)."""

    name: Name
    python: Name | None = None
    fmu: Name | None = None
    params: dict[str, Any] = {}
    period: str | int | float | None = None
    targets: Annotated[list[Name], Field(max_length=MAX_NAMES)] = []
    connect: list[list[Any]] = []


class AddModuleArgs(_Strict):
    module: ModuleSpec


class ConnectArgs(_Strict):
    src: Name
    dst: Name
    delay: bool = False


class DisconnectArgs(_Strict):
    dst: Name


class SnapshotRef(_Strict):
    snapshot: Annotated[int, Field(ge=0)]


class ForkArgs(_Strict):
    name: Annotated[str, Field(min_length=1, max_length=64)] | None = None


class ViewArgs(_Strict):
    signals: Names
    """Signal names or glob patterns (``core.*.q``), in the order the frame carries them."""


class ViewRef(_Strict):
    view: Annotated[int, Field(ge=0)]


class AcquireArgs(_Strict):
    lease: Annotated[float, Field(gt=0, le=3600)] = 30.0
    """Seconds the hold lasts without a call from its brain."""


class RobotRef(_Strict):
    robot: Name


Targets = Annotated[list[Number], Field(min_length=1, max_length=1024)] | dict[Name, Number]


class MotionArgs(_Strict):
    """Servo targets for a robot rig, to the simulation, the robot, or both (shadow mode)."""

    robot: Name
    targets: Targets
    """One value per joint of the rig, in its order, or ``{joint: value}`` for some of them."""
    route: Literal["sim", "robot", "both"] = "sim"
    sent_ns: int | None = None
    """Wall-clock time (ns since the epoch) the brain issued it; its age is checked against the deadline."""
    seq: Annotated[int, Field(ge=0)] | None = None


CALLS: dict[str, type[BaseModel]] = {
    "tick": TickArgs, "backtick": BacktickArgs, "start": StartArgs, "stop": NoArgs,
    "make": ObjectsArgs, "make_joint": MakeJointArgs, "remove_joint": NameArgs, "no_collision": ObjectsArgs,
    "place": PlaceArgs, "set": SetArgs, "get": NameArgs,
    "add_module": AddModuleArgs, "remove_module": NameArgs, "connect": ConnectArgs, "disconnect": DisconnectArgs,
    "snapshot": NoArgs, "restore": SnapshotRef, "drop_snapshot": SnapshotRef, "fork": ForkArgs, "close": NoArgs,
    "status": NoArgs, "view": ViewArgs, "read": ViewRef, "drop_view": ViewRef,
    "acquire": AcquireArgs, "release": NoArgs,
    "motion": MotionArgs, "robot_enable": RobotRef, "robot_stop": RobotRef, "robot_status": RobotRef,
}
"""Every call and the model of its arguments."""

READ_ONLY = frozenset({"status", "get", "read", "view", "drop_view", "robot_status"})
"""Calls any brain may make while another holds the world."""


class SetInput(_Strict):
    """``dynabrain/<world>/in/set``: values for unconnected inputs, applied at the next step boundary."""

    v: Literal[1] = 1
    brain: Annotated[str, Field(min_length=1, max_length=128)] | None = None
    values: Annotated[dict[Name, Value], Field(min_length=1, max_length=MAX_NAMES)]


class MotionInput(MotionArgs):
    """``dynabrain/<world>/in/motion``: a motion command as a stream (no reply)."""

    v: Literal[1] = 1
    brain: Annotated[str, Field(min_length=1, max_length=128)] | None = None


# -- replies -----------------------------------------------------------------------------------------------
class Reply(_Strict):
    """A successful reply (JSON): the tick after the call, the server instance and the call's result."""

    tick: int
    instance: int
    result: Any = None


ERROR_KINDS = ("bad_request", "unknown_call", "busy", "refused", "module_error", "rollback", "restarted",
               "closed", "internal")


class ErrorReply(_Strict):
    """An error reply (sent with Zenoh's reply_err): nothing was done, except for ``module_error``,
    where the failed tick was rolled back."""

    error: Literal[ERROR_KINDS]  # type: ignore[valid-type]
    message: str
    call: str | None = None
    instance: int | None = None


class WorldEventMsg(_Strict):
    """``dynabrain/<world>/events``: an edit, a rollback, an error, a brain or robot coming and going."""

    tick: int
    kind: str
    detail: dict[str, Any] = {}
    source: str = "api"


# -- decoding ----------------------------------------------------------------------------------------------
_RECENT: dict[tuple[str, bytes], tuple[Envelope, BaseModel]] = {}
"""Commands validated lately, by payload: a lock-step brain sends the same bytes again and again, and
the validated models are immutable, so they are looked up instead of parsed again."""
_RECENT_MAX = 512


def decode_command(call: str, payload: bytes) -> tuple[Envelope, BaseModel]:
    """The envelope and the validated arguments of ``call`` (one validation pass); raises `ProtocolError`."""
    hit = _RECENT.get((call, payload))
    if hit is not None:
        return hit
    model = _COMMANDS.get(call)
    if model is None:
        from dynabrain.orchestrator.kernel.suggest import did_you_mean

        raise ProtocolError(f"unknown call {call!r}" + did_you_mean(call, CALLS), "unknown_call")
    env = _parse(model, payload, MAX_COMMAND_BYTES, call)
    if len(payload) <= 512:
        if len(_RECENT) >= _RECENT_MAX:
            _RECENT.clear()
        _RECENT[(call, payload)] = (env, env.args)
    return env, env.args


def _command_model(call: str, args: type[BaseModel]) -> type[Envelope]:
    """The envelope of one call, with its arguments' model in place of ``args``."""
    return create_model(f"{args.__name__}Command_{call}", __base__=Envelope,
                        args=(args, Field(default_factory=args)))


_COMMANDS: dict[str, type[Envelope]] = {call: _command_model(call, model) for call, model in CALLS.items()}

def decode_input(model: type[BaseModel], payload: bytes, what: str) -> BaseModel:
    return _parse(model, payload, MAX_INPUT_BYTES, what)


def _parse(model: type[BaseModel], payload: bytes, limit: int, what: str) -> Any:
    if len(payload) > limit:
        raise ProtocolError(f"{what}: payload of {len(payload)} bytes is over the limit of {limit}")
    if not payload:
        return model()
    try:
        return model.model_validate_json(payload)
    except ValidationError as exc:
        raise ProtocolError(f"{what}: " + describe(exc)) from None


def describe(exc: ValidationError) -> str:
    """One line per problem: ``field.path: message``."""
    parts = []
    for err in exc.errors()[:8]:
        loc = ".".join(str(p) for p in err["loc"]) or "payload"
        parts.append(f"{loc}: {err['msg']}")
    more = exc.error_count() - len(parts)
    return "; ".join(parts) + (f"; and {more} more" if more > 0 else "")


def encode(obj: Any) -> bytes:
    """JSON bytes; NaN and infinities become null (plain JSON has no such numbers)."""
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:
        return json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False).encode()


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def plain(value: Any) -> Any:
    """A value as plain JSON types (numpy arrays and scalars to lists and floats)."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    return repr(value)


def schema() -> dict[str, Any]:
    """The JSON Schema of every JSON message (``protocol.schema.json``)."""
    defs: dict[str, Any] = {}
    calls: dict[str, Any] = {}
    for call, model in CALLS.items():
        calls[call] = {"$ref": f"#/$defs/{model.__name__}"}
    models = {m.__name__: m for m in (Envelope, Reply, ErrorReply, SetInput, MotionInput, WorldEventMsg,
                                      *CALLS.values())}
    for name, model in models.items():
        sub = model.model_json_schema(ref_template="#/$defs/{model}")
        defs.update(sub.pop("$defs", {}))
        defs[name] = sub
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://dynabrain.dev/bridge/protocol.schema.json",
        "title": f"dynabrain bridge protocol v{VERSION} (JSON messages)",
        "description": "Commands are queries on dynabrain/<world>/call/<call> with an Envelope whose `args` "
                       "follow the call's model (x-calls). Binary frames are described in PROTOCOL.md.",
        "x-calls": calls,
        "x-read-only-calls": sorted(READ_ONLY),
        "x-limits": {"command_bytes": MAX_COMMAND_BYTES, "input_bytes": MAX_INPUT_BYTES, "ticks": MAX_TICKS},
        "$defs": dict(sorted(defs.items())),
    }

