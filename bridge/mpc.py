"""Receding-horizon control of a world served over the bridge: the remote brain's MPC.

The same controller as `dynabrain.orchestrator.brain.mpc.Mpc` (its sampling, costs, warm start and
delay compensation), with the world on the other side of a `BrainClient`: the player module that plays
the plan is added to the served world by an ``add_module`` call (its class is one of dynabrain's own,
which a server allows by default), a replan starts its futures from a snapshot of the served world and
runs them on the server's batch backend (one ``batch`` call: the futures never cross the network, only
what they recorded), and a new plan is two ``set`` calls on the player. So a brain on a laptop plans
for a world (or a robot's twin) served elsewhere with the server's cores.

    client = BrainClient("swing_mpc", connect="tcp/127.0.0.1:7447")
    mpc = RemoteMpc(client, controls, cost, record=[...], horizon="1s", samples=32)
    mpc.run(duration="4s", every="100ms")          # in step: replan, tick 100 ms, replan...
    mpc.start(every="100ms"); ...; mpc.stop()       # or while the served world runs in real time

What stays local: the imagined future each replan chose (``mpc.futures``: the plan's start tick and its
recorded signals); the served world's own log has the plans, as parameter edits.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from dynabrain.orchestrator.brain.mpc import PLAYER, Mpc, MpcError, Replan, _first, _ticks
from dynabrain.orchestrator.kernel.errors import DynabrainError

from .client import BrainClient


class RemoteMpc(Mpc):
    """`Mpc` for a world served over the bridge (see the module docstring); ``client``: a connected
    `BrainClient` (it should hold the world: `BrainClient.acquire`)."""

    def __init__(self, client: BrainClient, controls: Any, cost: Any, **options: Any):
        if options.get("batch") is not None:
            raise MpcError("mpc: a served world runs its futures on the server's backend; give no batch")
        self.futures: list[tuple[int, dict[str, np.ndarray]]] = []
        super().__init__(client, controls, cost, **options)  # type: ignore[arg-type]

    # -- the served world ---------------------------------------------------------------------------------
    def _step_s(self) -> float:
        return int(self.world.status()["step_ns"]) * 1e-9

    def _now(self) -> int:
        return int(self.world.status()["tick"])

    def _make_batch(self, backend: str) -> None:
        return None

    def _latest(self) -> tuple[Any, int]:
        snap = self.world.snapshot()
        return snap, int(snap.tick)

    def _futures(self, start: Any, ticks: int, branches: int,
                 params: dict[str, Any]) -> tuple[dict[str, np.ndarray], Sequence[Any]]:
        plans = params[f"{self.player}.plan"]
        wire = {**params, f"{self.player}.plan": [np.asarray(p).tolist() for p in plans]}
        try:
            reply = self.world.batch(ticks, branches=branches, starts=start, params=wire, record=self.record,
                                     inputs={n: v.tolist() for n, v in self._assumed(ticks).items()},
                                     timeout=max(60.0, ticks * branches * 1e-4))
        finally:
            self.world.drop_snapshot(start)
        return reply.signals, reply.status

    def _check_world(self) -> None:
        if not self.controls:
            raise MpcError("mpc: give at least one control")
        for ch, control in self.controls.items():
            ports = [control.ports] if isinstance(control.ports, str) else list(control.ports)
            if not ch.isidentifier() or not ports or not control.low < control.high:
                raise MpcError(f"mpc: controls[{ch!r}]: an identifier, at least one port, low < high")
            for port in ports:
                self._exists(port, f"controls[{ch!r}]")
        for name in self.record:
            self._exists(name, "record")

    def _exists(self, name: str, what: str) -> None:
        try:
            self.world.get(name)
        except DynabrainError as exc:
            raise MpcError(f"mpc: {what}: {exc}") from None

    def _held(self) -> np.ndarray:
        return np.array([float(self.world.get(_first(self.controls[ch].ports))) for ch in self.channels])

    def _attach(self) -> None:
        if self.player in self.world.status()["modules"]:
            return
        self.world.add_module({"name": self.player, "python": PLAYER,
                               "params": {"channels": ",".join(self.channels), "hold": self._held().tolist(),
                                          "units": ",".join(self._units())}})
        for ch in self.channels:
            ports = self.controls[ch].ports
            for port in [ports] if isinstance(ports, str) else ports:
                self.world.connect(f"{self.player}.{ch}", port)

    def _units(self) -> list[str]:
        """Radians for a servo's angle inputs, else no unit: what the served ports are in (the server
        checks them when the player is connected)."""
        return ["rad" if ".q_ref" in _first(self.controls[ch].ports) else "1" for ch in self.channels]

    # -- playing ------------------------------------------------------------------------------------------
    def apply(self, plan: Replan, *, at_tick: int | None = None) -> None:
        """Set ``plan`` on the served world's player (see `Mpc.apply`); its future is kept in ``futures``."""
        now = self._now()
        start = plan.tick + plan.delay_ticks if at_tick is None else at_tick
        if now < start:
            rows = np.concatenate([self.rows_from(now, start - now), plan.values])
        else:
            rows = plan.values[min(now - start, len(plan.values) - 1):]
            if now > start:
                self.stats.late += 1
                self.stats.worst_late_s = max(self.stats.worst_late_s, (now - start) * self.dt)
        self.world.set(f"{self.player}.plan", rows.tolist())
        self.world.set(f"{self.player}.start", now * self.dt)
        self._plan_start_tick, self._plan_values = now, rows
        if plan.signals:
            self.futures.append((plan.tick + plan.delay_ticks, plan.signals))

    def run(self, world: Any = None, duration: int | float | str = "1s", *,
            every: int | float | str = "100ms") -> Any:
        """Closed loop in step with the served world: replan, tick ``every``, repeat, for ``duration``."""
        total, each = _ticks(self.dt, duration, "duration"), _ticks(self.dt, every, "every")
        end = self._now() + total
        now = self._now()
        while now < end:
            self.apply(self.replan())
            n = min(each, end - now)
            self.world.tick(n)
            self.stats.ticks += n
            now += n
        return self.stats

    # -- while the served world runs (`Mpc.start`: the same loop, over the bridge) -------------------------
    POLL_S = 0.02  # (each look is a status call)

    def _running(self) -> bool:
        return bool(self.world.status()["server"]["loop"]["running"])

    def _tick_of(self, state: Any) -> int:
        return int(state.tick)
