"""Receding-horizon control on imagined futures: predictive sampling, CEM and MPPI over a `Batch`.

At each replan the brain samples input sequences around its current plan (spline knots over a
horizon), rolls them out from the world's latest state as one batch of futures, scores each with the
user's cost on what the futures recorded, and makes the best (or, for MPPI, the cost-weighted mean)
its new plan. The world plays the plan's first part while the next replan is thought out, warm-started
from this one (after MJPC's predictive sampling, and the sampling planners of hydrax and judo; here the
futures are whole co-simulations: physics, robot modules and FMUs).

    mpc = Mpc(world, {"hip": Control(["servo.l_hip_pitch.q_ref", "servo.r_hip_pitch.q_ref"], -1.2, 0.2)},
              cost=lambda f: -f.last("core.swing_pivot.q") ** 2, record=["core.swing_pivot.q"],
              horizon="1s", knots=4, samples=32, method="mppi")
    report = mpc.run(world, "16s", every="100ms")        # replan, play 100 ms of it, replan, ...
    mpc.start(world, every="100ms")                      # the same while the world runs in real time
    ...; mpc.stop()

How the plan reaches the world: a `PlanPlayer` module (``modules.playback``; added and connected by
the controller, named ``mpc`` unless told otherwise) plays the plan's rows onto the controlled ports,
one row a tick, and holds the last row when the plan runs out. A new plan is a parameter set on the
player, so history and the log keep it: a rollback to a tick under a plan plays it again. In the futures the
brain imagines, the same player plays each sample (its ``plan`` a per-branch parameter).

While the world runs (`start`): the planner works in a thread of its own on the latest state and never
holds the world's lock longer than it takes to export the state and set the plan. It compensates its
own delay: each future first plays, for as many ticks as the last replan took, the plan the world is
playing meanwhile, and the new plan is scored from there, from the state predicted for the tick at
which it will be applied. When a replan comes later than that the plan still takes over at once (its
first rows skipped); how far behind real time the planner is shows in `MpcStats`.

Robust to what the brain does not know: ``randomize`` draws values of run-time parameters (friction,
a servo gain) for ``draws`` variants of every sample; a sample's cost is the ``aggregate`` over them
(the mean, the worst, or the CVaR: the mean of the worst ``cvar`` fraction). What the brain assumes of
inputs it does not control is ``assume`` (port -> value held in every future: a push it felt is not
assumed to go on; without it a future starts with the inputs as the world has them now).

Each replan's chosen future (the best sample's recorded signals) is kept as a future the world
imagined (`World.imagine`), which a logged run writes to ``/imagined/<name>/0/...``.

Failure: a branch that fails (its physics diverges, a module raises) costs infinity; a cost function
that raises or returns the wrong shape raises `MpcError` naming the replan's tick, and the world is
left as it was (no plan is set); controls, parameters or signals that do not exist are refused when the
controller is made, before anything runs.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.world import World
from .batch import Batch
from .mpc_parts import (
    PLAYER,
    Control,
    Futures,
    MpcError,
    MpcStats,
    Replan,
    _check_options,
    _finite,
    _first,
    _state_tick,
    _ticks,
)


class Mpc:
    """Receding-horizon control of ``world`` through ``controls`` (name -> `Control`); see the module
    docstring. ``cost``: a function of `Futures` returning one cost a future; ``record``: the signals it
    reads; ``horizon``: ticks, or a duration (``"1s"``, seconds as a float); ``knots``: spline knots over
    the horizon (values between them are interpolated linearly); ``samples``: futures a replan;
    ``method``: ``sampling`` (keep the best), ``cem`` (refit a Gaussian to the elite fraction
    ``elite``, ``iterations`` times) or ``mppi`` (the cost-weighted mean, ``temperature`` relative to the
    spread of the costs); ``randomize``: run-time parameter -> (low, high), drawn uniformly for
    ``draws`` variants of every sample, the cost aggregated by ``aggregate`` (``cvar``: the mean of the
    worst ``cvar`` fraction); ``batch`` or ``backend``: where the futures run; ``player``: the name of
    the module that plays the plan; ``seed``: the sampler's generator."""

    POLL_S = 0.005
    """How often `start`'s planner looks whether the world has gone far enough for the next replan."""

    def __init__(self, world: World, controls: Mapping[str, Control], cost: Callable[[Futures], Any], *,
                 record: Sequence[str] = (), horizon: int | float | str = "1s", knots: int = 4, samples: int = 32,
                 method: str = "mppi", iterations: int = 1, elite: float = 0.25, temperature: float = 0.1,
                 randomize: Mapping[str, tuple[float, float]] | None = None, draws: int = 1,
                 assume: Mapping[str, Any] | None = None,
                 aggregate: str = "mean", cvar: float = 0.25, batch: Batch | None = None, backend: str = "auto",
                 player: str = "mpc", seed: int = 0, name: str = "mpc"):
        self.world = world
        self.dt = self._step_s()
        self.horizon = _ticks(self.dt, horizon, "horizon")
        _check_options(knots, samples, method, iterations, elite, temperature, draws, aggregate, cvar, self.horizon)
        self.controls = dict(controls)
        self.channels = list(self.controls)
        self.cost, self.record = cost, list(record)
        self.knots, self.samples, self.method = int(knots), int(samples), method
        self.iterations, self.elite, self.temperature = int(iterations), float(elite), float(temperature)
        self.randomize = dict(randomize or {})
        self.assume = {name: np.asarray(value, dtype=np.float64) for name, value in (assume or {}).items()}
        self.draws, self.aggregate, self.cvar = int(draws), aggregate, float(cvar)
        self.player, self.name = player, name
        self.rng = np.random.default_rng(seed)
        self._check_world()
        self.low = np.array([float(self.controls[c].low) for c in self.channels])
        self.high = np.array([float(self.controls[c].high) for c in self.channels])
        self.noise = np.array([float(self.controls[c].noise) if self.controls[c].noise is not None
                               else 0.25 * (h - lo) for c, lo, h in zip(self.channels, self.low, self.high,
                                                                          strict=True)])
        self._attach()
        self.reset()
        self._own_batch = batch is None
        self.batch = batch if batch is not None else self._make_batch(backend)
        self.stats = MpcStats()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None

    # -- the world: where the futures start and run, where the plan plays (`bridge.mpc` serves the same
    # -- controller a world over the bridge by overriding these) ------------------------------------------
    def _step_s(self) -> float:
        return self.world.dt_ns * 1e-9

    def _now(self) -> int:
        return self.world.tick_count

    def _make_batch(self, backend: str) -> Any:
        return Batch(self.world, backend=backend)

    def _running(self) -> bool:
        """Whether the world's loop runs (`World.start`)."""
        return self.world.running

    def _tick_of(self, state: Any) -> int:
        return _state_tick(state)

    def _latest(self) -> tuple[Any, int]:
        """The world's latest state (what `_futures` starts from) and its tick."""
        with self.world.lock():
            return self.world.export_state(), self.world.tick_count

    def _futures(self, start: Any, ticks: int, branches: int,
                 params: dict[str, Any]) -> tuple[dict[str, np.ndarray], Sequence[Any]]:
        """Run ``branches`` futures from ``start``; (recorded signals, how each branch ended: a
        `BranchStatus` each)."""
        result = self.batch.run(ticks, branches=branches, starts=start, params=params, record=self.record,
                                inputs=self._assumed(ticks), keep_states=False)
        return result.signals, result.status

    def _assumed(self, ticks: int) -> dict[str, np.ndarray]:
        """The ``assume`` inputs held over ``ticks`` ticks of every future."""
        return {name: np.broadcast_to(value, (ticks, *value.shape)) for name, value in self.assume.items()}

    # -- set-up -------------------------------------------------------------------------------------------
    def _check_world(self) -> None:
        if not self.controls:
            raise MpcError("mpc: give at least one control")
        for ch, control in self.controls.items():
            if not isinstance(control, Control):
                raise MpcError(f"mpc: controls[{ch!r}] is a {type(control).__name__}; give a Control(ports, low, high)")
            if not ch.isidentifier():
                raise MpcError(f"mpc: the control name {ch!r} must be an identifier (it names a port of the player)")
            lo, hi = control.low, control.high
            if not (_finite(lo) and _finite(hi) and lo < hi):
                raise MpcError(f"mpc: controls[{ch!r}]: bounds {lo!r} .. {hi!r}; two finite numbers, low < high")
            if control.noise is not None and not (_finite(control.noise) and control.noise > 0):
                raise MpcError(f"mpc: controls[{ch!r}].noise is {control.noise!r}; a number above 0")
            ports = [control.ports] if isinstance(control.ports, str) else list(control.ports)
            if not ports:
                raise MpcError(f"mpc: controls[{ch!r}] drives no port")
            for port in ports:
                try:
                    target = self._port(port)
                except DynabrainError as exc:
                    raise MpcError(f"mpc: controls[{ch!r}]: {exc}") from None
                if not isinstance(target, str):
                    raise MpcError(f"mpc: controls[{ch!r}]: {port!r} is a parameter, not an input port")
                if self.world.signal_shape(target) != ():
                    raise MpcError(f"mpc: controls[{ch!r}]: {port!r} is not a scalar port; name its elements")
        for name in self.record:
            try:
                self.world.signal_shape(name)
            except DynabrainError as exc:
                raise MpcError(f"mpc: record: {exc}") from None
        for name, value in self.assume.items():
            try:
                target = self.world.settable(name)
            except DynabrainError as exc:
                raise MpcError(f"mpc: assume: {exc}") from None
            if not isinstance(target, str):
                raise MpcError(f"mpc: assume: {name!r} is a parameter; assume holds input ports")
            if value.shape != self.world.signal_shape(target):
                raise MpcError(f"mpc: assume[{name!r}] has shape {value.shape}; the port's is "
                               f"{self.world.signal_shape(target)}")
        for name, bounds in self.randomize.items():
            if self.world.material_target(name) is None:
                try:
                    target = self.world.settable(name)
                except DynabrainError as exc:
                    raise MpcError(f"mpc: randomize: {exc}") from None
                if isinstance(target, str):
                    raise MpcError(f"mpc: randomize: {name!r} is an input port; randomize run-time parameters")
            if not (isinstance(bounds, (tuple, list)) and len(bounds) == 2 and all(_finite(b) for b in bounds)
                    and bounds[0] <= bounds[1]):
                raise MpcError(f"mpc: randomize[{name!r}] is {bounds!r}; give (low, high)")

    def _port(self, port: str) -> str | tuple:
        """A controlled port's full name (an unconnected input, or one the player drives already: a
        second controller on the same world and channels)."""
        player = self.world.modules.get(self.player)
        if player is None:
            return self.world.settable(port)
        if type(player).__name__ != "PlanPlayer" or player.params["channels"] != ",".join(self.channels):
            raise MpcError(f"mpc: the world has a module {self.player!r} that is not this controller's player "
                           f"(channels {','.join(self.channels)}); name another with player=")
        self.world.signal_shape(port)
        for conn in self.world.connections:
            if conn.dst == port and conn.src.startswith(f"{self.player}."):
                return conn.dst
        return self.world.settable(port)

    def _held(self) -> np.ndarray:
        """The controlled ports' values now (the first of each channel's ports)."""
        return np.array([float(self.world.get(_first(self.controls[ch].ports))) for ch in self.channels])

    def _attach(self) -> None:
        """The player module that plays the plan, connected to every controlled port (once)."""
        if self.player in self.world.modules:
            return
        from ..scenario.make import make_module  # the one place modules are made from specs

        units = ",".join(self._unit(self.world.settable(_first(self.controls[ch].ports))) for ch in self.channels)
        spec = {"name": self.player, "python": PLAYER, "params": {"channels": ",".join(self.channels),
                                                                  "hold": self._held().tolist(), "units": units}}
        self.world.add_module(make_module(spec))
        for ch in self.channels:
            ports = self.controls[ch].ports
            for port in [ports] if isinstance(ports, str) else ports:
                self.world.connect(f"{self.player}.{ch}", self.world.settable(port))

    def _unit(self, port: str) -> str:
        module, _, name = port.partition(".")
        for p in self.world.modules[module].inputs():
            if p.name == name:
                return p.unit
        return "1"

    def reset(self) -> None:
        """Forget the plan: start again from the controlled ports' values now (after the world was restored
        to an earlier state, a warm start from a plan made for another time would jolt it)."""
        self.mean = np.tile(np.clip(self._held(), self.low, self.high), (self.knots, 1))
        self.std = np.tile(self.noise, (self.knots, 1))
        self._plan_start_tick = self._now()
        self._plan_values = np.tile(self.mean[0], (self.horizon, 1))

    # -- one replan -----------------------------------------------------------------------------------------
    def values(self, knots: np.ndarray) -> np.ndarray:
        """Per-tick values over the horizon ``(..., ticks, channels)`` of knots ``(..., knots, channels)``:
        linear between knots spread evenly over the horizon, clipped to the bounds."""
        t = np.linspace(0.0, self.knots - 1, self.horizon)
        lo = np.minimum(np.floor(t).astype(int), self.knots - 2) if self.knots > 1 else np.zeros(self.horizon, int)
        frac = (t - lo)[:, None]
        if self.knots == 1:
            out = np.repeat(knots[..., :1, :], self.horizon, axis=-2)
        else:
            out = knots[..., lo, :] * (1 - frac) + knots[..., lo + 1, :] * frac
        return np.clip(out, self.low, self.high)

    def replan(self, state: bytes | None = None, *, delay_ticks: int = 0, prefix: np.ndarray | None = None) -> Replan:
        """Plan from ``state`` (default: the world's now), ``delay_ticks`` later: the futures first play
        ``prefix`` (the rows the world will play meanwhile; default the current plan's), then the
        samples. Updates the controller's plan (not the world's: see `apply`)."""
        t0 = time.perf_counter()
        state, tick = self._latest() if state is None else (state, self._tick_of(state))
        if delay_ticks > 0 and prefix is None:
            prefix = self.rows_from(tick, delay_ticks)
        prefix = np.zeros((0, len(self.channels))) if prefix is None else np.asarray(prefix, dtype=np.float64)
        self._shift(tick + len(prefix))
        draws = self._draws()
        best: tuple[float, np.ndarray, dict[str, np.ndarray], np.ndarray] | None = None
        failed = 0
        costs = np.zeros(0)
        for _ in range(self.iterations):
            knots = self._sample()
            rows = self.values(knots)
            costs, signals, fails = self._evaluate(state, tick, prefix, rows, draws)
            failed += fails
            b = int(np.argmin(costs))
            if best is None or costs[b] < best[0]:
                best = (float(costs[b]), knots[b], {n: v[b * self.draws] for n, v in signals.items()}, rows[b])
            self._update(knots, costs)
        assert best is not None
        chosen = best[1] if self.method != "mppi" else self.mean.copy()
        if self.method != "mppi":
            self.mean = chosen.copy()
        wall = time.perf_counter() - t0
        self.stats.replans += 1
        self.stats.wall_s.append(wall)
        self.stats.costs.append(best[0])
        return Replan(chosen, self.values(chosen), best[0], costs, best[2], tick, len(prefix), wall, failed)

    def _sample(self) -> np.ndarray:
        """``samples`` knot sets: the current plan first, the rest Gaussian around it."""
        noise = self.rng.standard_normal((self.samples - 1, self.knots, len(self.channels))) * self.std
        return np.concatenate([self.mean[None], np.clip(self.mean[None] + noise, self.low, self.high)])

    def _draws(self) -> list[dict[str, float]]:
        """The variants of the randomised parameters for this replan (common to every sample)."""
        if not self.randomize:
            return [{}]
        return [{name: float(self.rng.uniform(lo, hi)) for name, (lo, hi) in self.randomize.items()}
                for _ in range(self.draws)]

    def _evaluate(self, state: Any, tick: int, prefix: np.ndarray, rows: np.ndarray,
                  draws: list[dict[str, float]]) -> tuple[np.ndarray, dict[str, np.ndarray], int]:
        n, d = len(rows), len(draws)
        plans = np.concatenate([np.broadcast_to(prefix, (n, *prefix.shape)), rows], axis=1) if len(prefix) else rows
        plans = np.repeat(plans, d, axis=0)
        params: dict[str, Any] = {f"{self.player}.plan": list(plans), f"{self.player}.start": tick * self.dt}
        for name in self.randomize:
            params[name] = [draws[k % d][name] for k in range(n * d)]
        ticks = len(prefix) + self.horizon
        recorded, status = self._futures(state, ticks, n * d, params)
        ok = np.array([s.ok for s in status])
        if not ok.any():  # nothing to choose from: not a plan of infinite cost
            raise MpcError(f"mpc: every future of the replan of tick {tick} failed; the first: {status[0]}")
        skip = len(prefix)
        signals = {name: v[:, skip:] for name, v in recorded.items()}
        controls = {ch: np.repeat(rows[:, :, k], d, axis=0) for k, ch in enumerate(self.channels)}
        try:
            raw = np.asarray(self.cost(Futures(signals, controls, self.dt)), dtype=np.float64)
        except Exception as exc:  # the user's function: its error, named with the replan
            raise MpcError(f"mpc: the cost function raised at the replan of tick {tick}: "
                           f"{type(exc).__name__}: {exc}") from exc
        if raw.shape != (n * d,):
            raise MpcError(f"mpc: the cost function returned shape {raw.shape} at the replan of tick {tick}; it "
                           f"returns one cost a future, shape ({n * d},)")
        raw = np.where(ok & np.isfinite(raw), raw, np.inf)
        return self._aggregate(raw.reshape(n, d)), signals, int((~ok).sum())

    def _aggregate(self, costs: np.ndarray) -> np.ndarray:
        if costs.shape[1] == 1:
            return costs[:, 0]
        if self.aggregate == "mean":
            return costs.mean(axis=1)
        if self.aggregate == "worst":
            return costs.max(axis=1)
        k = max(1, math.ceil(self.cvar * costs.shape[1]))
        return np.sort(costs, axis=1)[:, -k:].mean(axis=1)

    def _update(self, knots: np.ndarray, costs: np.ndarray) -> None:
        finite = np.isfinite(costs)
        if not finite.any():
            return
        if self.method == "cem":
            k = max(2, math.ceil(self.elite * len(costs)))
            elite = knots[np.argsort(costs)[:k]]
            self.mean = elite.mean(axis=0)
            self.std = np.maximum(elite.std(axis=0), 0.05 * self.noise)
        elif self.method == "mppi":
            c = np.where(finite, costs, np.nanmax(np.where(finite, costs, np.nan)))
            spread = float(np.std(c)) or 1.0
            w = np.exp(-(c - c.min()) / (self.temperature * spread))
            w[~finite] = 0.0
            self.mean = np.tensordot(w / w.sum(), knots, axes=1)

    def _shift(self, tick: int) -> None:
        """Warm start: the plan's knots moved on to start at ``tick`` (the last knot held)."""
        elapsed = tick - self._plan_start_tick
        if elapsed <= 0 or self.knots == 1:
            return
        step = (self.horizon - 1) / (self.knots - 1)
        at = np.arange(self.knots) * step + elapsed
        old = self.values(self.mean)
        self.mean = old[np.minimum(np.round(at).astype(int), self.horizon - 1)]
        if self.method == "cem":
            self.std = np.tile(self.noise, (self.knots, 1))

    # -- playing ------------------------------------------------------------------------------------------
    def rows_from(self, tick: int, count: int) -> np.ndarray:
        """The rows the world plays at ticks ``tick`` .. ``tick + count - 1`` under the current plan."""
        idx = np.clip(np.arange(tick, tick + count) - self._plan_start_tick, 0, len(self._plan_values) - 1)
        return self._plan_values[idx]

    def apply(self, plan: Replan, *, at_tick: int | None = None) -> None:
        """Set ``plan`` on the world's player: it takes over at ``at_tick`` (default the tick it was planned
        for; the rows before it are the current plan's, the rows already past are skipped). Keeps its
        future as imagined."""
        w = self.world
        with w.lock():
            now = w.tick_count
            start = plan.tick + plan.delay_ticks if at_tick is None else at_tick
            if now < start:
                rows = np.concatenate([self.rows_from(now, start - now), plan.values])
            else:
                rows = plan.values[min(now - start, len(plan.values) - 1):]
                late = (now - start) * self.dt
                if now > start:
                    self.stats.late += 1
                    self.stats.worst_late_s = max(self.stats.worst_late_s, late)
            w.set(f"{self.player}.plan", rows)
            w.set(f"{self.player}.start", now * self.dt)
            self._plan_start_tick, self._plan_values = now, rows
            if plan.signals:
                w.imagine(self.name, plan.tick + plan.delay_ticks, plan.signals)

    def run(self, world: World | None = None, duration: int | float | str = "1s", *,
            every: int | float | str = "100ms") -> MpcStats:
        """Closed loop in step with the world: replan from its state, play ``every`` of the plan, repeat,
        for ``duration`` (ticks or a duration). Returns the statistics."""
        w = world or self.world
        if w is not self.world:
            raise MpcError("mpc: run the world the controller was made for")
        total, each = _ticks(self.dt, duration, "duration"), _ticks(self.dt, every, "every")
        end = w.tick_count + total
        while w.tick_count < end:
            self.apply(self.replan())
            n = min(each, end - w.tick_count)
            w.tick(n)
            self.stats.ticks += n
        return self.stats

    def start(self, world: World | None = None, *, every: int | float | str = "100ms") -> None:
        """Replan in a thread while the world runs (`World.start`; started here in real time if it is not
        running): every ``every`` of simulated time, or as soon as the last replan is done when that took
        longer. `stop` ends it; an error in the planner stops it and `stop` raises it."""
        w = world or self.world
        if w is not self.world:
            raise MpcError("mpc: run the world the controller was made for")
        if self._thread is not None:
            raise MpcError("mpc: already running; stop it first")
        each = _ticks(self.dt, every, "every")
        self._stop.clear()
        self._error = None
        if not self._running():
            w.start(realtime=True)
        self._thread = threading.Thread(target=self._loop, args=(each,), name=f"mpc {self.name}", daemon=True)
        self._thread.start()

    def _loop(self, each: int) -> None:
        delay = each
        poll_s = min(self.POLL_S, each * self.dt / 4)
        try:
            while not self._stop.is_set() and self._running():
                state, tick = self._latest()
                plan = self.replan(state, delay_ticks=delay)
                self.apply(plan)
                took = max(1, math.ceil(plan.wall_s / self.dt))
                delay = took  # the next plan starts where the world will be when it is ready
                while not self._stop.is_set() and self._running() and self._now() < tick + max(each, took):
                    time.sleep(poll_s)
        except BaseException as exc:  # reported by stop()
            self._error = exc

    def stop(self) -> MpcStats:
        """Stop replanning (the world keeps running on the last plan); raises what stopped the planner."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
        if self._error is not None:
            err, self._error = self._error, None
            raise err
        return self.stats

    def close(self) -> None:
        """Stop, and close the batch if the controller made it."""
        try:
            self.stop()
        finally:
            if self._own_batch:
                self.batch.close()

    def __enter__(self) -> Mpc:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
