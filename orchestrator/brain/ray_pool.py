"""The ``ray`` backend: the batch's workers as Ray actors, on a local Ray or on a cluster.

Each actor is a `BranchRunner` (a world of its own, built with the batch's ``build``) and runs one
branch at a time; a finished actor takes the next branch. An actor that dies fails the branch it was
running, with Ray's reason, and is replaced. Ray is an optional extra: ``pip install 'dynabrain[ray]'``.

On other hosts: start a head (``ray start --head --port=6379``) and workers (``ray start
--address=HEAD:6379``) with dynabrain installed and the scenario files at the same paths, then
``Batch(world, backend="ray", address="HEAD:6379")``.

Token authentication (on by default since Ray 2.5x): the head makes a token (``ray get-auth-token``
prints it); this process joins with it when it has one where Ray looks (``RAY_AUTH_TOKEN``,
``RAY_AUTH_TOKEN_PATH``, ``~/.ray/auth_token``). Ray itself uses such a token unasked only for a local
cluster it finds (``address="auto"``); for an explicit address dynabrain turns token mode on the same
way (`maybe_enable_token_auth_if_token_available`, unless ``RAY_AUTH_MODE`` says otherwise). When
joining fails, the error names the likely cause: nothing at the address, no token or another token,
another Ray or Python version.
"""

from __future__ import annotations

import contextlib
import socket
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from ..kernel.branch import BranchOutcome, BranchRunner, BranchStatus, BranchTask
from ..kernel.errors import DynabrainError

CONNECT_TIMEOUT_S = 10
IN_FLIGHT = 2
"""Branches handed to one actor at a time: the one it runs and the next."""
"""How long the first contact with a cluster may take (a TCP connection to its address)."""


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise DynabrainError("batch backend 'ray' needs Ray: pip install 'dynabrain[ray]'") from None
    return ray


def connect(address: str | None) -> Any:
    """Ray, initialised: joined to the cluster at ``address``, or a local Ray when None (an existing
    connection is kept). A cluster that cannot be joined is an error naming the address and the likely
    cause (see the module docstring)."""
    ray = _ray()
    if ray.is_initialized():
        return ray
    token = False
    if address is not None and address != "auto":
        _probe(address)
        token = _token_mode()
    try:
        if address is None:  # a local Ray: it advertises loopback (its servers still bind Ray's own way)
            ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False,
                     _node_ip_address="127.0.0.1")
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
    except Exception as exc:
        raise DynabrainError(f"batch backend 'ray': cannot join the Ray cluster at {address!r}: "
                             f"{_cause(exc, token)}") from None
    return ray


def _token_mode() -> bool:
    """Whether this process joins with a token: `RAY_AUTH_MODE`, else whether it has one (then Ray's token
    mode is turned on for it, as Ray does for a local cluster)."""
    try:
        from ray._private.authentication.authentication_token_setup import (
            maybe_enable_token_auth_if_token_available,
        )
    except ImportError:  # a Ray without token authentication
        return False
    return bool(maybe_enable_token_auth_if_token_available(warn_if_disabled=False))


def _cause(exc: BaseException, token: bool) -> str:
    """What most likely kept this process out of a cluster that answers at its address."""
    text = str(exc).splitlines()[0] if str(exc) else ""
    said = f"{type(exc).__name__}: {text}"
    if "version" in text.lower():
        return f"another Ray or Python version runs there ({said})"
    if isinstance(exc, ConnectionError) and not token:
        return (f"it answers but let this process in on no token ({said}); Ray clusters ask for one by default: "
                "give this process the head's (`ray get-auth-token` there) as RAY_AUTH_TOKEN, in the file "
                "RAY_AUTH_TOKEN_PATH names, or in ~/.ray/auth_token")
    if isinstance(exc, ConnectionError):
        return (f"it answers but refused this process's token ({said}); is it the head's (RAY_AUTH_TOKEN, "
                "RAY_AUTH_TOKEN_PATH, ~/.ray/auth_token)?")
    return said


def _probe(address: str) -> None:
    """Fail fast when nothing answers at ``address`` (Ray itself retries for minutes)."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        with socket.create_connection((host or "127.0.0.1", int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except (OSError, ValueError) as exc:
        raise DynabrainError(f"batch backend 'ray': cannot reach the Ray cluster at {address!r}: "
                             f"{exc.strerror if isinstance(exc, OSError) and exc.strerror else exc}") from None


class RayPool:
    """``size`` actors (default: the cluster's CPUs) building their worlds with ``build``."""

    def __init__(self, build: Callable[[], Any], size: int | None, address: str | None):
        self.ray = ray = connect(address)
        self.build = build
        self.size = size or max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.replaced = 0
        self._runner = ray.remote(num_cpus=1, max_restarts=0)(BranchRunner)
        self._actors = [self._runner.remote(build) for _ in range(self.size)]
        try:  # a world that cannot be built is an error now, not a failed branch later
            ray.get([actor.__ray_ready__.remote() for actor in self._actors])
        except Exception as exc:
            self.close()
            raise DynabrainError(f"batch backend 'ray': a worker could not build its world: {_reason(exc)}") from None

    def map(self, tasks: Sequence[BranchTask]) -> list[BranchOutcome]:
        """Every task's outcome, in the order of ``tasks``. Each actor has up to `IN_FLIGHT` branches
        handed to it (Ray runs an actor's calls one after the other, in order), so it starts its next
        branch while the driver takes the last one's outcome."""
        ray = self.ray
        queue = deque(tasks)
        handed: dict[Any, deque[Any]] = {actor: deque() for actor in self._actors}  # refs, in the order given
        owner: dict[Any, tuple[Any, BranchTask]] = {}
        outcomes: dict[int, BranchOutcome] = {}

        def feed(actor: Any) -> None:
            refs = handed[actor]
            while queue and len(refs) < IN_FLIGHT:
                task = queue.popleft()
                ref = actor.run.remote(task)
                refs.append(ref)
                owner[ref] = (actor, task)

        for actor in self._actors:
            feed(actor)
        while owner:
            done, _ = ray.wait(list(owner), num_returns=1)
            for ref in done:
                if ref not in owner:  # a branch given back to the queue with its actor's death (below)
                    continue
                actor, task = owner[ref]
                try:
                    outcomes[task.index] = ray.get(ref)
                except ray.exceptions.RayActorError as exc:
                    # the first branch handed to it was running; those after it never started: they go
                    # back to the queue, for the actor that takes its place
                    first, *later = handed.pop(actor)
                    running = owner.pop(first)[1]
                    outcomes[running.index] = BranchOutcome(running.index, {}, None, BranchStatus(
                        False, f"the Ray worker running branch {running.index} died ({_reason(exc)})", lost=True))
                    for other in reversed(later):
                        queue.appendleft(owner.pop(other)[1])
                    actor = self._replace(actor)
                    handed[actor] = deque()
                    feed(actor)
                    continue
                except ray.exceptions.RayError as exc:
                    outcomes[task.index] = BranchOutcome(task.index, {}, None, BranchStatus(
                        False, f"branch {task.index} failed in Ray: {_reason(exc)}"))
                del owner[ref]
                handed[actor].remove(ref)
                feed(actor)
        return [outcomes[t.index] for t in tasks]

    def _replace(self, dead: Any) -> Any:
        fresh = self._runner.remote(self.build)
        self._actors[self._actors.index(dead)] = fresh
        self.replaced += 1
        return fresh

    def close(self) -> None:
        for actor in self._actors:
            with contextlib.suppress(Exception):  # already gone
                self.ray.kill(actor)
        self._actors = []


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__
