"""The bridge's wire format, JSON part: key expressions, command envelopes, the arguments of every call,
replies, errors and brain inputs. `PROTOCOL.md` describes it; `protocol.schema.json` and the table of
calls in `PROTOCOL.md` are generated from these models and `TABLE` (``python -m dynabrain.bridge.schema``)
and every incoming JSON message is validated by them. Binary frames (state, robot) are in `frames`.

`TABLE` is the one list of calls: each call's argument model and how the server treats it. The server
dispatches through it (`handlers`: ``do_<call>`` of `WorldService` or of `BridgeServer`, checked against
the table once per class), the client validates what it sends against it, and the schema and the
document are written from it.

Every model refuses unknown fields and wrong types (strict: ``"1"`` is not an int) and non-finite numbers
in its number fields (``NaN``, ``Infinity``, ``1e999``); a payload larger than its limit is refused before it
is parsed. Values a model leaves open (``set``'s value, a module's params, ``batch``'s inputs) are checked
by the server (`checks`).
"""

from __future__ import annotations

import functools
import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
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
MAX_BATCH_BYTES = 8 * 1024 * 1024
"""Largest ``batch`` command accepted (its inputs are arrays of ticks), under the session's 16 MiB messages."""
MAX_BATCH_BRANCHES = 4096
"""Most branches of one ``batch`` call (each server also caps branches x ticks: ``--batch-max-ticks``)."""
MAX_UNTIL_S = 1e9
"""Latest simulated time (s) a ``start`` may run until."""
TOKENLESS_LEASE_S = 10.0
"""Default lease (s) of a hold whose brain has no liveliness token (``dynabrain serve --tokenless-lease``)."""
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
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)


Name = Annotated[str, Field(min_length=1, max_length=256)]
Names = Annotated[list[Name], Field(min_length=1, max_length=MAX_NAMES)]
Number = float | int
Quantity = Number | Annotated[str, Field(min_length=1, max_length=64)]
"""A number in SI units, or a string with its unit (``"100mm"``, ``"50g"``)."""
MAX_MESH_VERTICES = 20_000
"""Most vertices of a mesh body (as `kernel.meshes.MAX_VERTICES`; the command's bytes limit comes first)."""
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
    until: Annotated[float, Field(ge=0, le=MAX_UNTIL_S)] | None = None
    """Stop by itself at this simulated time (s)."""


class ObjectsArgs(_Strict):
    objects: Names


class MakeArgs(_Strict):
    objects: Names
    others: Literal["frozen", "absent"] = "frozen"
    """What becomes of the objects not selected: frozen where they stand, or out of the simulation."""


class MakeJointArgs(_Strict):
    a: Name
    b: Name
    name: Name | None = None
    kind: Name = "weld"
    """``weld`` (rigid), ``hinge``, ``slider`` or ``ball`` (the core refuses another, naming the kinds)."""
    axis: Annotated[list[Quantity], Field(min_length=3, max_length=3)] | None = None
    """World frame; a hinge turns about it, a slider slides along it (default z)."""
    anchor: Annotated[list[Quantity], Field(min_length=3, max_length=3)] | None = None
    """World frame, lengths in m or with a unit (``"120mm"``); default: b's origin."""


Point = Annotated[list[Number], Field(min_length=3, max_length=3)]
Triangle = Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=3, max_length=3)]


class MeshData(_Strict):
    """A mesh written out: vertices in the body frame (m, before ``scale``) and triangles (optional: the
    convex hull is what both cores simulate). A file on the server is never read."""

    vertices: Annotated[list[Point], Field(min_length=4, max_length=MAX_MESH_VERTICES)]
    faces: Annotated[list[Triangle], Field(max_length=2 * MAX_MESH_VERTICES)] = []


class AddBodyArgs(_Strict):
    """A body to add while the world runs: `BodySpec`'s fields, with the units and colour names of a
    scenario file (``"100mm"``, ``"50g"``, ``"blue"``), checked by the world."""

    name: Name
    shape: Name
    """``box``, ``sphere``, ``capsule``, ``cylinder`` or ``mesh``."""
    size: Annotated[list[Quantity], Field(max_length=3)] = []
    pos: Annotated[list[Quantity], Field(min_length=3, max_length=3)] = [0.0, 0.0, 0.0]
    quat: Annotated[list[Number], Field(min_length=4, max_length=4)] | None = None
    mass: Quantity | None = None
    color: Name | Annotated[list[Number], Field(min_length=3, max_length=4)] | None = None
    friction: Annotated[float, Field(ge=0)] | Annotated[int, Field(ge=0)] | None = None
    restitution: Annotated[float, Field(ge=0, le=1)] | Annotated[int, Field(ge=0, le=1)] | None = None
    mesh: MeshData | None = None
    scale: Number | Annotated[list[Number], Field(min_length=3, max_length=3)] | None = None
    joint: Literal["free", "fixed"] | None = None
    """``fixed``: held where it is put; default free."""


class MaterialArgs(_Strict):
    """A body's own coefficients; a field left out keeps its value, null gives back the core's."""

    body: Name
    friction: Annotated[float, Field(ge=0)] | Annotated[int, Field(ge=0)] | None = None
    restitution: Annotated[float, Field(ge=0, le=1)] | Annotated[int, Field(ge=0, le=1)] | None = None
    mass: Annotated[float, Field(gt=0, le=1e6)] | Annotated[int, Field(gt=0, le=1_000_000)] | None = None


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
    """Seconds the hold lasts without a call from its brain (at most the server's tokenless lease, 10 s by
    default, while the brain has no liveliness token)."""


SnapshotId = Annotated[int, Field(ge=0)]


class BatchArgs(_Strict):
    """N futures of the served world stepped together (`dynabrain.orchestrator.brain.Batch`); the world
    itself is not changed."""

    ticks: Annotated[int, Field(ge=1, le=MAX_TICKS)]
    branches: Annotated[int, Field(ge=1, le=MAX_BATCH_BRANCHES)] | None = None
    """How many futures; may be left out when ``starts`` lists one snapshot per branch."""
    starts: SnapshotId | Annotated[list[SnapshotId], Field(min_length=1, max_length=MAX_BATCH_BRANCHES)] | None = None
    """Where the branches start: null (the world now), a snapshot id (every branch), or one id per branch."""
    inputs: Annotated[dict[Name, list[Any]], Field(max_length=MAX_NAMES)] = {}
    """Input port -> finite numbers of shape ``(ticks, *port)`` (every branch) or ``(branches, ticks, *port)``."""
    params: Annotated[dict[Name, Value], Field(max_length=MAX_NAMES)] = {}
    """Run-time parameter -> one value for every branch, or a list of one value per branch."""
    record: Annotated[list[Name], Field(max_length=MAX_NAMES)] = []
    """Signals to return, each ``(branches, ticks, *shape)``: row k is the value after tick k+1."""
    keep_states: bool = False
    """Keep each branch's final state as a new snapshot of the served world (``restore`` continues from it)."""


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


@dataclass(frozen=True, slots=True)
class Call:
    """One call of the protocol (an entry of `TABLE`)."""

    model: type[BaseModel]
    """Its arguments (the envelope's ``args``)."""
    takes: str
    """Its arguments, in words (`PROTOCOL.md`)."""
    returns: str
    """Its result, in words."""
    read_only: bool = False
    """Any brain may make it while another holds the world."""
    server: bool = False
    """Answered by the server (holds, forks, the loop, robots, the server's status): ``BridgeServer.do_<call>``;
    otherwise by the world: ``WorldService.do_<call>``."""
    slow: bool = False
    """Always run on the server's worker thread (it may take long), never on the Zenoh thread that delivered it."""
    max_bytes: int = MAX_COMMAND_BYTES
    """Largest command payload accepted for it."""

    @property
    def doc(self) -> str:
        """Its arguments and result in one line (the schema's description of the call)."""
        return "; ".join(f"{what}: {text}" for what, text in (("args", self.takes), ("result", self.returns)) if text)


TABLE: dict[str, Call] = {
    "tick": Call(TickArgs, "`n` (1..1e6, default 1), `view` (optional)",
                 "null, or the view's STATE frame after the ticks; a `stop` ends a long one early (error "
                 "`stopped`, with the ticks done)"),
    "backtick": Call(BacktickArgs, "`n` (default 1)", "null; the world as it was `n` ticks ago, exactly"),
    "start": Call(StartArgs, "`realtime` (false, true, or a speed factor), `until` (s, optional)",
                  "`{running, realtime, until_tick}`", server=True),
    "stop": Call(NoArgs, "", "`{running: false, error, stopped}`: ends the loop and a `tick` running on this world "
                 "(`stopped`: `{brain, ticks_done, ticks_asked}` of that tick, or null)", server=True),
    "make": Call(MakeArgs, "`objects` (names or glob patterns), `others` (`frozen` (default): the others stay as "
                 "static obstacles; `absent`: out of the simulation)", "the selection"),
    "make_joint": Call(MakeJointArgs, "`a`, `b`, `name` (optional), `kind` (`weld` (default), `hinge`, `slider`, "
                       "`ball`), `axis` [3] and `anchor` [3] (world frame, optional)", "the joint's name"),
    "remove_joint": Call(NameArgs, "`name`", ""),
    "no_collision": Call(ObjectsArgs, "`objects`", ""),
    "add_body": Call(AddBodyArgs, "`name`, `shape` (`box`, `sphere`, `capsule`, `cylinder`, `mesh`), `size`, `pos`, "
                     "`quat`, `mass`, `color` (a name or RGB(A)), `friction`, `restitution`, `mesh` (`{vertices, "
                     "faces}`), `scale`, `joint` (`free` or `fixed`); numbers in SI or strings with units",
                     "`{body, signals}`: its name and its new signals", slow=True),
    "remove_body": Call(NameArgs, "`name` (an object)", "`{disconnected}`: the connections to its ports, dropped",
                        slow=True),
    "set_material": Call(MaterialArgs, "`body`, `friction`, `restitution`, `mass` (kg) (each optional; null: the "
                         "core's, the model's own mass)", "`{friction, restitution, mass}`: the body's own, now"),
    "place": Call(PlaceArgs, "`body`, `pos` [3], `quat` [4] (optional)", ""),
    "set": Call(SetArgs, "`name` (`module.param` or an unconnected input `module.port`), `value` (lists of numbers "
                "are arrays; a list holding objects or strings, such as a servo's `sequence` of `{pose, duration}` "
                "steps, goes to the module as it is)", ""),
    "get": Call(NameArgs, "`name` (a signal or a parameter)", "the value", read_only=True),
    "add_module": Call(AddModuleArgs, "`module`: the scenario's module syntax "
                       "`{name, python | fmu, params, period, targets, connect}`", "`{module, order}`", slow=True),
    "remove_module": Call(NameArgs, "`name`", "the schedule order"),
    "connect": Call(ConnectArgs, "`src`, `dst`, `delay` (default false)", ""),
    "disconnect": Call(DisconnectArgs, "`dst`", ""),
    "snapshot": Call(NoArgs, "", "`{snapshot: id, tick, evicted}` (the server keeps 64; older ones are evicted)"),
    "restore": Call(SnapshotRef, "`snapshot`", ""),
    "drop_snapshot": Call(SnapshotRef, "`snapshot`", ""),
    "batch": Call(BatchArgs, "`ticks`, `branches`, `starts` (null, a snapshot id, or one per branch), `inputs` "
                  "(`{port: (ticks, *port) or (branches, ticks, *port) numbers}`), `params` (`{name: value or one per "
                  "branch}`), `record` (signals), `keep_states` (default false); the command may be 8 MiB",
                  "a BATCH frame: the recorded arrays `(branches, ticks, *shape)`, each branch's status, and with "
                  "`keep_states` each final state's new snapshot id; the world is unchanged", slow=True,
                  max_bytes=MAX_BATCH_BYTES),
    "fork": Call(ForkArgs, "`name` (optional)", "`{world: <fork name>, tick}`", server=True, slow=True),
    "close": Call(NoArgs, "(on a fork)", "", server=True, slow=True),
    "status": Call(NoArgs, "", "the world's status, its stream layout, robots, and `server` (brains, holder, forks, "
                   "loop, `running`: the tick running and how far it got)", read_only=True, server=True),
    "view": Call(ViewArgs, "`signals` (names or patterns, in order)",
                 "`{view: id, size, signals: [{name, shape, unit, offset}]}`", read_only=True),
    "read": Call(ViewRef, "`view`", "a STATE frame", read_only=True),
    "drop_view": Call(ViewRef, "`view`", "", read_only=True),
    "acquire": Call(AcquireArgs, "`lease` (s, default 30; at most 10 while the brain has no liveliness token)",
                    "`{holder, lease}`", server=True),
    "release": Call(NoArgs, "", "`{holder: null}`", server=True),
    "motion": Call(MotionArgs, "`robot`, `targets` (a list in the rig's joint order, or `{joint: value}`), `route` "
                   "(`sim`, `robot`, `both`), `sent_ns`, `seq`",
                   "`{sim: ..., robot: {forwarded, seq, age_ms} or {forwarded: false, reason} (too old) or "
                   "{forwarded: false, ignored: true, reason} (the robot is disabled or safe-stopped)}`", server=True),
    "robot_enable": Call(RobotRef, "`robot`", "`{sent, enable_window_ms}`: a move or program must reach the robot "
                         "within the enable window, or it safe-stops", server=True),
    "robot_stop": Call(RobotRef, "`robot`", "", server=True),
    "robot_status": Call(RobotRef, "`robot`", "link state (`alive`, `lost_tick`, `mode`, `mode_tick`, `reason`), "
                         "counts, the last program and the robot's word on it, the last measured state, shadow "
                         "statistics", read_only=True, server=True),
}
"""Every call of the protocol (`PROTOCOL.md` lists them in this order)."""

CALLS: dict[str, type[BaseModel]] = {name: call.model for name, call in TABLE.items()}
"""Every call and the model of its arguments (from `TABLE`)."""

READ_ONLY = frozenset(name for name, call in TABLE.items() if call.read_only)
"""Calls any brain may make while another holds the world (from `TABLE`)."""

SLOW = frozenset(name for name, call in TABLE.items() if call.slow)
"""Calls always run on the server's worker thread (from `TABLE`)."""


def handlers(owner: object, *, server: bool) -> dict[str, Callable[..., Any]]:
    """``{call: owner.do_<call>}`` for every call of `TABLE` that ``owner`` answers: the server's calls
    (``server``) or the world's. Raises `TypeError` when one of them has no ``do_`` method, or a ``do_``
    method is no such call (checked once per class)."""
    return {name: getattr(owner, f"do_{name}") for name in _handled(type(owner), server)}


@functools.cache
def _handled(cls: type, server: bool) -> tuple[str, ...]:
    wanted = [name for name, call in TABLE.items() if call.server == server]
    have = {attr[3:] for attr in dir(cls) if attr.startswith("do_") and callable(getattr(cls, attr))}
    missing, extra = [n for n in wanted if n not in have], sorted(have - set(wanted))
    side = "server" if server else "world"
    problems = ([f"no do_<call> for {', '.join(missing)}"] if missing else []) + \
               ([f"do_<call> for what is no {side} call: {', '.join(extra)}"] if extra else [])
    if problems:
        raise TypeError(f"{cls.__name__} does not match the bridge's table of calls ({side} calls): "
                        + "; ".join(problems))
    return tuple(wanted)


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
               "closed", "stopped", "internal")


class ErrorReply(_Strict):
    """An error reply (sent with Zenoh's reply_err): nothing was done, except for ``module_error``,
    where the ticks before the failed one stay and the failed one was rolled back, and ``stopped``,
    where a ``stop`` ended a ``tick`` early and the ticks done stay."""

    error: Literal[ERROR_KINDS]  # type: ignore[valid-type]
    message: str
    call: str | None = None
    instance: int | None = None
    detail: dict[str, Any] | None = None
    """``stopped``: ``{ticks_done, ticks_asked, tick, by}`` (the world's tick after the call, the stopping brain)."""


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

        raise ProtocolError(f"unknown call {call!r}" + did_you_mean(call, TABLE), "unknown_call")
    env = _parse(model, payload, TABLE[call].max_bytes, call)
    if len(payload) <= 512:
        if len(_RECENT) >= _RECENT_MAX:
            _RECENT.clear()
        _RECENT[(call, payload)] = (env, env.args)
    return env, env.args


def _command_model(call: str, args: type[BaseModel]) -> type[Envelope]:
    """The envelope of one call, with its arguments' model in place of ``args``."""
    return create_model(f"{args.__name__}Command_{call}", __base__=Envelope,
                        args=(args, Field(default_factory=args)))


_COMMANDS: dict[str, type[Envelope]] = {name: _command_model(name, call.model) for name, call in TABLE.items()}

def decode_input(model: type[BaseModel], payload: bytes, what: str) -> BaseModel:
    return _parse(model, payload, MAX_INPUT_BYTES, what)


def _parse(model: type[BaseModel], payload: bytes, limit: int, what: str) -> Any:
    if len(payload) > limit:
        raise ProtocolError(f"{what}: payload of {len(payload)} bytes is over the limit of {limit}")
    try:
        return model.model_validate_json(payload) if payload else model()
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
    for name, call in TABLE.items():
        calls[name] = {"$ref": f"#/$defs/{call.model.__name__}", **({"description": call.doc} if call.doc else {})}
    models = {m.__name__: m for m in (Envelope, Reply, ErrorReply, SetInput, MotionInput, WorldEventMsg,
                                      *(call.model for call in TABLE.values()))}
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
        "x-limits": {"command_bytes": MAX_COMMAND_BYTES, "input_bytes": MAX_INPUT_BYTES, "ticks": MAX_TICKS,
                     "batch_bytes": MAX_BATCH_BYTES, "batch_branches": MAX_BATCH_BRANCHES},
        "$defs": dict(sorted(defs.items())),
    }

