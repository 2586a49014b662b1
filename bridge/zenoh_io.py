"""The one place that speaks Zenoh's configuration words: sessions for servers, brains and robots.

Defaults (see `Settings`): an embedded *peer* on loopback, multicast scouting off, gossip off, an
explicit listen endpoint on the server and explicit connect endpoints on clients. Anything else (a
router, TLS, user/password, access control) comes from a Zenoh JSON5 configuration file
(``bridge/zenoh-secure.json5`` is a commented example); our defaults fill only what the file leaves
unset, and explicit settings (``listen``, ``connect``, ``user``) override the file.

A listen endpoint with port 0 gets a free port chosen here (Zenoh does not tell which port it bound),
so a server can report the endpoint clients must use.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
from collections.abc import Sequence
from dataclasses import dataclass, field

import zenoh

from .errors import ConnectError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
_TCP = re.compile(r"^(tcp|tls|quic)/(\[[^\]]+\]|[^:/\[]+):(\d+)(#.*)?$")


@dataclass
class Settings:
    """How to open a Zenoh session."""

    listen: Sequence[str] = ()
    """Endpoints to listen on (``tcp/127.0.0.1:7447``; port 0 picks a free port)."""
    connect: Sequence[str] = ()
    """Endpoints to connect to (a server's listen endpoint, or a router's)."""
    config_file: str | None = None
    """A Zenoh JSON5 configuration file (router, TLS, user/password, access control)."""
    mode: str | None = None
    """``peer`` (default) or ``client`` (through a router)."""
    user: str | None = None
    password: str | None = None
    lease_ms: int | None = None
    """How long a silent peer is kept before it counts as gone (Zenoh's default is 10 s)."""
    connect_timeout_ms: int = 2000
    shared_memory: bool | None = None
    """Zenoh's shared-memory transport between processes on one host: None leaves Zenoh's default (on in
    1.x: a message of `shm_threshold` bytes or more goes through shared memory when both ends can),
    False turns it off, True turns it on."""
    shm_threshold: int | None = None
    """Smallest message (bytes) the transport moves to shared memory (Zenoh's default: 3072)."""
    extra: dict[str, object] = field(default_factory=dict)
    """Further Zenoh configuration keys (``"transport/link/rx/max_message_size": 16777216``)."""


def build_config(s: Settings) -> zenoh.Config:
    """A Zenoh configuration from settings (file first, then our defaults where it is silent)."""
    if s.config_file is not None:
        if not os.path.exists(s.config_file):
            raise ConnectError(f"Zenoh configuration file {s.config_file!r} not found")
        try:
            conf = zenoh.Config.from_file(s.config_file)
        except Exception as exc:
            raise ConnectError(f"Zenoh configuration file {s.config_file!r} is not valid: {exc}") from None
    else:
        conf = zenoh.Config()
    defaults = {"mode": "peer", "scouting/multicast/enabled": False, "scouting/gossip/enabled": False,
                "transport/link/rx/max_message_size": 16 * 1024 * 1024}
    for key, value in defaults.items():
        if _unset(conf, key):
            _put(conf, key, value)
    if s.mode is not None:
        _put(conf, "mode", s.mode)
    if s.listen or s.config_file is None:
        _put(conf, "listen/endpoints", list(s.listen))
    if s.connect or s.config_file is None:
        _put(conf, "connect/endpoints", list(s.connect))
    if s.connect:
        _put(conf, "connect/timeout_ms", s.connect_timeout_ms)
        _put(conf, "connect/exit_on_failure", True)
    if s.user is not None:
        _put(conf, "transport/auth/usrpwd/user", s.user)
        _put(conf, "transport/auth/usrpwd/password", s.password or "")
    if s.shared_memory is not None:
        _put(conf, "transport/shared_memory/enabled", bool(s.shared_memory))
    if s.shm_threshold is not None:
        _put(conf, "transport/shared_memory/transport_optimization/message_size_threshold", int(s.shm_threshold))
    if s.lease_ms is not None:
        _put(conf, "transport/link/tx/lease", int(s.lease_ms))
    for key, value in s.extra.items():
        _put(conf, key, value)
    return conf


def _unset(conf: zenoh.Config, key: str) -> bool:
    try:
        return json.loads(conf.get_json(key)) is None
    except Exception:  # a key this Zenoh does not know: leave it to its defaults
        return False


def _put(conf: zenoh.Config, key: str, value: object) -> None:
    try:
        conf.insert_json5(key, json.dumps(value))
    except Exception as exc:
        raise ConnectError(f"Zenoh configuration key {key!r} = {value!r} refused: {exc}") from None


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
        sock.bind((host.strip("[]"), 0))
        return int(sock.getsockname()[1])


def _ephemeral(endpoint: str) -> re.Match | None:
    m = _TCP.match(endpoint)
    return m if m and m.group(3) == "0" else None


def resolve_listen(endpoints: Sequence[str]) -> list[str]:
    """Endpoints with port 0 replaced by a free port."""
    out = []
    for ep in endpoints:
        m = _ephemeral(ep)
        out.append(f"{m.group(1)}/{m.group(2)}:{free_port(m.group(2))}{m.group(4) or ''}" if m else ep)
    return out


def open_session(s: Settings, *, retries: int = 4) -> tuple[zenoh.Session, list[str]]:
    """Open a session; returns it and the endpoints it listens on. A port-0 endpoint that another
    process takes between the choice and the bind is chosen again (``retries`` times)."""
    last: Exception | None = None
    for _ in range(retries + 1):
        listen = resolve_listen(s.listen)
        conf = build_config(Settings(**{**s.__dict__, "listen": listen}))
        try:
            return zenoh.open(conf), listen or _configured_listen(conf)
        except Exception as exc:  # zenoh raises ZError with its own text
            last = exc
            if s.connect or not any(_ephemeral(ep) for ep in s.listen):
                break
    raise ConnectError(diagnose(s, last)) from None


def _configured_listen(conf: zenoh.Config) -> list[str]:
    """The listen endpoints a config file gave (Zenoh's own defaults are a dict by mode: not ours to tell)."""
    try:
        value = json.loads(conf.get_json("listen/endpoints"))
    except Exception:
        return []
    return [str(ep) for ep in value] if isinstance(value, list) else []


def diagnose(s: Settings, exc: Exception | None) -> str:
    """Why a session could not be opened, in words: nothing listening, or the peer refused us."""
    text = str(exc).split(" at /", 1)[0] if exc is not None else "unknown error"
    if s.connect:
        reachable = [ep for ep in s.connect if _reachable(ep)]
        if not reachable:
            return (f"no world answered: nothing listens at {', '.join(s.connect)} "
                    f"(is `dynabrain serve` running there?) [{text}]")
        auth = "with the user/password given" if s.user else "without credentials"
        return (f"the endpoint {reachable[0]} accepts connections but refused the Zenoh session {auth}: "
                f"wrong credentials, or a TLS / access-control setting that does not match [{text}]")
    if s.listen:
        return f"cannot listen on {', '.join(s.listen)}: {text}"
    return f"cannot open a Zenoh session: {text}"


def _reachable(endpoint: str) -> bool:
    m = _TCP.match(endpoint)
    if not m:
        return True  # not TCP-like: cannot probe, assume reachable
    host, port = m.group(2).strip("[]"), int(m.group(3))
    with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.5):
        return True
    return False


def payload_bytes(zbytes: zenoh.ZBytes | None) -> bytes:
    return b"" if zbytes is None else zbytes.to_bytes()


JSON = zenoh.Encoding.APPLICATION_JSON
FRAME = zenoh.Encoding("application/octet-stream;dynabrain.frame.v1")
