"""Processes for testing bridges for real: a served world, a robot emulator or a brain script, each a
separate Python process on loopback, started and reaped with their output kept for error messages.

    with ServerProcess("bridge/arm.yaml") as server:
        with BrainClient("arm", connect=server.endpoint) as brain:
            brain.tick(10)

`serving` is the same in this process (a `BridgeServer` on a world the test holds, a real Zenoh session
on loopback), for tests that look at the world while a brain drives it.
"""

from __future__ import annotations

import contextlib
import os
import re
import selectors
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from dynabrain.orchestrator.kernel.errors import DynabrainError

_ENDPOINT = re.compile(r" on ((?:tcp|tls|quic)/\S+)")


class Process:
    """A child process whose first stdout line says it is ready."""

    def __init__(self, args: Sequence[str], *, ready: str, timeout: float = 30.0, cwd: str | None = None,
                 env: dict[str, str] | None = None):
        self.args = [sys.executable, *args]
        self._ready_word, self._timeout = ready, timeout
        self._cwd, self._env = cwd, env
        self.proc: subprocess.Popen | None = None
        self.ready_line = ""
        self.output = ""

    def start(self) -> Process:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **(self._env or {})}
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     cwd=self._cwd, env=env)
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        end = time.monotonic() + self._timeout
        lines = []
        while time.monotonic() < end:
            if not sel.select(timeout=max(end - time.monotonic(), 0.01)):
                continue
            line = self.proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if self._ready_word in line:
                self.ready_line = line
                return self
        self.kill()
        raise DynabrainError(f"{' '.join(self.args[1:4])} did not get ready in {self._timeout:g} s:\n"
                             + "".join(lines) + self.output)

    @property
    def pid(self) -> int:
        return self.proc.pid if self.proc else -1

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout: float = 15.0) -> str:
        """SIGTERM, wait, and return what it printed after its ready line."""
        if self.proc is None:
            return self.output
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        self.output += out or ""
        return self.output

    def wait(self, timeout: float = 60.0) -> tuple[int, str]:
        """Wait for it to end by itself; (exit code, what it printed after its ready line)."""
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            raise DynabrainError(f"{' '.join(self.args[1:4])} did not end in {timeout:g} s:\n{self.output}") from None
        self.output += out or ""
        return self.proc.returncode, self.output

    def kill(self) -> None:
        """SIGKILL: the process vanishes without closing anything (a crash, a pulled cable)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            with contextlib.suppress(Exception):
                out, _ = self.proc.communicate(timeout=10)
                self.output += out or ""

    def freeze(self) -> None:
        """SIGSTOP: a frozen peer (its sockets stay open, it answers nothing)."""
        self.proc.send_signal(signal.SIGSTOP)

    def thaw(self) -> None:
        self.proc.send_signal(signal.SIGCONT)

    def __enter__(self) -> Process:
        return self.start() if self.proc is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ServerProcess(Process):
    """``dynabrain serve SCENARIO --listen tcp/127.0.0.1:0 ...`` in a child process."""

    def __init__(self, scenario: str, *extra: str, listen: str = "tcp/127.0.0.1:0", **kw):
        args = ["-m", "dynabrain.orchestrator.cli", "serve", scenario, *(["--listen", listen] if listen else []),
                *extra]
        super().__init__(args, ready="serving world", **kw)

    @property
    def endpoint(self) -> str:
        m = _ENDPOINT.search(self.ready_line)
        if not m:
            raise DynabrainError(f"no endpoint in {self.ready_line!r}")
        return m.group(1)

    @property
    def instance(self) -> int:
        return int(self.ready_line.rsplit("instance", 1)[1])


class EmulatorProcess(Process):
    """``dynabrain robot-emulator SCENARIO --world W --connect EP ...`` in a child process."""

    def __init__(self, scenario: str, world: str, connect: str, *extra: str, **kw):
        args = ["-m", "dynabrain.orchestrator.cli", "robot-emulator", scenario, "--world", world,
                "--connect", connect, *extra]
        super().__init__(args, ready="ready", **kw)


@contextlib.contextmanager
def serving(world: Any, name: str, timeout: float = 20.0) -> Iterator[tuple[Any, Any]]:
    """(server, brain): ``world`` served in this process on a loopback port, and a `BrainClient` called
    ``name`` connected to it; the server and the world are closed after."""
    from .client import BrainClient
    from .server import BridgeServer, ServeOptions
    from .zenoh_io import Settings

    server = BridgeServer(world, Settings(listen=["tcp/127.0.0.1:0"]), ServeOptions())
    try:
        server.open()
        with BrainClient(name, connect=server.endpoints, timeout=timeout) as brain:
            yield server, brain
    finally:
        server.close()
        world.close()


def wait_for(predicate: Callable[[], Any], timeout: float = 5.0, what: str = "condition",
             between: Callable[[], None] | None = None) -> Any:
    """Poll ``predicate`` every 20 ms until it returns something true, and return that; ``between`` runs
    between polls. An `AssertionError` naming ``what`` after ``timeout`` seconds (a liveness bound for
    tests, not a timing)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        if between is not None:
            between()
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")
