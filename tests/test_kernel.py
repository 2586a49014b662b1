"""The kernel's own logic: schedule, wiring checks, history and rollback, fork, threads, observers.

These tests use small signal modules (the orchestrator's logic is what is under test); the physics
core's rollback is tested with real MuJoCo in test_rollback_physics.py. Every test runs with the
generated tick and with the plain loop (`tick_runner` in conftest.py).
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from dynabrain.modules.basic import Constant, Counter, Gain, Integrator, Noise, Sine
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.errors import AlgebraicLoopError, ModuleError, RollbackError, WiringError
from dynabrain.orchestrator.kernel.module import Capabilities, Module, Param, Port
from dynabrain.orchestrator.kernel.observers import Observer
from dynabrain.orchestrator.kernel.world import World

pytestmark = pytest.mark.usefixtures("tick_runner")  # every test both ways: generated tick, plain loop


class Tracer(Module):
    """Appends (tick, name) to a shared list when it steps; one input, one output (feedthrough)."""

    def __init__(self, name, log, **kw):
        super().__init__(name, **kw)
        self.log = log

    def inputs(self):
        return (Port("u", ()),)

    def outputs(self):
        return (Port("y", ()),)

    def step(self, t_ns, dt_ns):
        self.log.append((t_ns // 1_000_000, self.name, dt_ns // 1_000_000))
        self.out["y"][...] = self.inp["u"] + 1


class Boom(Module):
    PARAMS = ()

    def __init__(self, name, at_tick, **kw):
        super().__init__(name, **kw)
        self.at_tick = at_tick

    def step(self, t_ns, dt_ns):
        if t_ns // 1_000_000 == self.at_tick:
            raise ValueError("boom")


class NoRollback(Counter):
    CAPABILITIES = Capabilities(can_rollback=False, can_fork=False)


def test_schedule_golden_trace_multirate():
    log: list = []
    w = World(step="1ms")
    # added in an order that is not the data-flow order: c <- b <- a
    w.add_module(Tracer("c", log), period="3ms")
    w.add_module(Tracer("b", log), period="2ms")
    w.add_module(Tracer("a", log))
    w.connect("a.y", "b.u")
    w.connect("b.y", "c.u")
    assert w.schedule_order() == ["a", "b", "c"]
    w.tick(7)
    assert log == [
        (0, "a", 1), (0, "b", 2), (0, "c", 3),
        (1, "a", 1),
        (2, "a", 1), (2, "b", 2),
        (3, "a", 1), (3, "c", 3),
        (4, "a", 1), (4, "b", 2),
        (5, "a", 1),
        (6, "a", 1), (6, "b", 2), (6, "c", 3),
    ]
    # values flow within a tick (Gauss-Seidel): c sees b's output of the same tick
    assert w.get("a.y") == 1.0 and w.get("b.y") == 2.0 and w.get("c.y") == 3.0


def test_late_module_steps_on_its_own_phase():
    log: list = []
    w = World(step="1ms")
    w.add_module(Tracer("a", log))
    w.tick(3)
    w.add_module(Tracer("late", log), period="2ms")
    w.tick(4)
    assert [t for t, n, _ in log if n == "late"] == [3, 5]


def test_algebraic_loop_reported_with_path():
    w = World()
    w.add_module(Gain("g1"))
    w.add_module(Gain("g2"))
    w.connect("g1.y", "g2.u")
    with pytest.raises(AlgebraicLoopError) as err:
        w.connect("g2.y", "g1.u")
    assert "g1.y -> g2.u" in str(err.value) and "g2.y -> g1.u" in str(err.value)
    assert len(w.connections) == 1  # the world is unchanged
    w.connect("g2.y", "g1.u", delay=True)  # an explicit delay breaks it
    w.tick(3)


def test_loop_through_a_state_module_is_not_algebraic():
    w = World()
    w.add_module(Integrator("i", x0=1.0))
    w.add_module(Gain("k", k=-1.0))
    w.connect("i.y", "k.u")
    w.connect("k.y", "i.u")
    w.tick(1000)  # x' = -x, dt = 2 ms, 2 s
    assert abs(w.get("i.y")[0] - np.exp(-2.0)) < 0.01


@pytest.mark.parametrize(("src", "dst", "message"), [
    ("nope.y", "g.u", "no module 'nope'"),
    ("s.yy", "g.u", "no output port 'yy' (did you mean 'y'?)"),
    ("g.u", "s.y", "is an input"),
    ("v.y", "g.u", "shape mismatch"),
])
def test_wiring_errors(src, dst, message):
    w = World()
    w.add_module(Sine("s"))
    w.add_module(Gain("g"))
    w.add_module(Integrator("v", n=3))
    with pytest.raises(WiringError, match=None) as err:
        w.connect(src, dst)
    assert message in str(err.value)


def test_unit_mismatch_and_double_driver():
    w = World()
    w.add_module(Constant("s", unit="m"))
    w.add_module(Gain("g", unit="N"))
    w.add_module(Gain("h"))
    with pytest.raises(WiringError, match="unit mismatch"):
        w.connect("s.y", "g.u")
    w.add_module(Integrator("i"))
    w.connect("i.y", "h.u")
    with pytest.raises(WiringError, match="driven twice"):
        w.connect("h.y", "h.u")


def test_bad_period_and_duplicate_name():
    w = World(step="2ms")
    with pytest.raises(WiringError, match="not a whole multiple"):
        w.add_module(Counter("c"), period="3ms")
    w.add_module(Counter("c"))
    with pytest.raises(WiringError, match="used twice"):
        w.add_module(Counter("c"))


def _world() -> World:
    w = World(step="1ms", seed=7, history=50)
    w.add_module(Noise("n", n=2, sigma=0.5))
    w.add_module(Integrator("i", n=2))
    w.add_module(Gain("g", n=2, k=3.0))
    w.connect("n.y", "i.u")
    w.connect("i.y", "g.u")
    return w


def test_backtick_then_tick_is_bit_identical():
    w = _world()
    w.tick(10)
    frames = []
    for _ in range(20):
        w.tick()
        frames.append(w.bus.copy())
    w.backtick(20)
    assert w.tick_count == 10
    for frame in frames:
        w.tick()
        assert np.array_equal(w.bus, frame)


def test_backtick_restores_structure_and_params():
    w = _world()
    w.tick(5)
    w.set("g.k", 10.0)
    w.add_module(Counter("c"))
    w.tick(5)
    w.remove_module("n")
    w.tick(5)
    assert "n" not in w.modules and w.get("c.count") == 10.0
    w.backtick(10)  # back to tick 5, after the edits made at tick 5
    assert set(w.modules) == {"n", "i", "g", "c"} and w.get("g.k") == 10.0 and w.get("c.count") == 0.0
    w.backtick(1)  # tick 4: before the edits
    assert set(w.modules) == {"n", "i", "g"} and w.get("g.k") == 3.0
    assert w.connections[0].src == "n.y"


def test_rollback_errors():
    w = _world()
    w.tick(3)
    with pytest.raises(RollbackError, match="beyond the history"):
        w.backtick(4)
    w.add_module(NoRollback("nr"))
    w.tick(2)
    with pytest.raises(RollbackError, match="nr cannot roll back"):
        w.backtick(1)
    w.backtick(3)  # tick 2, before the module was added (at tick 3): allowed, nothing of it to restore
    assert "nr" not in w.modules


def test_exception_in_step_rolls_back_and_names_module():
    w = World(step="1ms")
    w.add_module(Counter("c"))
    w.add_module(Boom("bomb", at_tick=5))
    w.tick(5)
    before = w.bus.copy()
    with pytest.raises(ModuleError) as err:
        w.tick()
    assert err.value.module == "bomb" and err.value.tick == 5 and "boom" in str(err.value)
    assert w.tick_count == 5 and np.array_equal(w.bus, before)
    w.remove_module("bomb")  # the world stays usable
    w.tick(3)
    assert w.get("c.count") == 8.0


def test_the_failing_module_is_named_among_many_of_the_same_kind_and_rates():
    w = World(step="1ms")
    w.add_module(Counter("c"))
    for name, at, period in (("b1", 8, None), ("b2", 6, "2ms"), ("b3", 7, None)):
        w.add_module(Boom(name, at_tick=at), period=period)
    w.add_module(Counter("late"), period="3ms")
    w.tick(6)
    with pytest.raises(ModuleError) as err:
        w.tick()
    assert (err.value.module, err.value.tick) == ("b2", 6) and w.tick_count == 6
    w.remove_module("b2")
    with pytest.raises(ModuleError) as err:
        w.tick(2)
    assert (err.value.module, err.value.tick) == ("b3", 7) and w.get("c.count") == 7.0


class Latch(Module):
    """Counts its steps while ``hold`` is off; its steps leave its state alone while ``hold`` is on."""

    PARAMS = (Param("hold", True, runtime=True),)

    def __init__(self, name, **kw):
        super().__init__(name, **kw)
        self.asked = 0

    def outputs(self):
        return (Port("y", ()),)

    def start(self, t_ns):
        self._count = 0

    def step(self, t_ns, dt_ns):
        if not self.params["hold"]:
            self._count += 1
        self.out["y"][...] = self._count

    def get_state(self):
        self.asked += 1
        return self._count

    def set_state(self, state):
        self._count = state

    def steps_change_state(self):
        return not self.params["hold"]


def test_a_module_whose_steps_leave_its_state_alone_is_saved_once_and_rolls_back_exactly():
    w = World(step="1ms", keyframe_every=1)  # a state every tick: the saves counted are per tick
    latch = Latch("l")
    w.add_module(latch)
    w.add_module(Counter("c"))
    w.tick(10)
    assert latch.asked <= 2  # saved once for the stretch (and once when it joined)
    frames = []
    for hold, ticks in ((False, 10), (True, 10), (False, 5)):
        w.set("l.hold", hold)
        asked = latch.asked
        for _ in range(ticks):
            w.tick()
            frames.append((w.bus.copy(), latch._count))
        assert latch.asked - asked >= ticks if not hold else latch.asked - asked <= 2
    assert latch._count == 15
    w.backtick(25)  # back across both switches
    assert latch._count == 0 and w.get("l.y") == 0.0
    replay = []
    for hold, ticks in ((False, 10), (True, 10), (False, 5)):
        w.set("l.hold", hold)
        for _ in range(ticks):
            w.tick()
            replay.append((w.bus.copy(), latch._count))
    assert all(np.array_equal(a, b) and n == m for (a, n), (b, m) in zip(frames, replay, strict=True))
    w.backtick(7)  # into the held stretch: the state kept for it comes back
    assert latch._count == 10 and w.get("l.y") == 10.0
    w.backtick(10)  # into the counting stretch
    assert latch._count == 8 and not w.modules["l"].params["hold"]


def test_snapshot_restore_and_fork_independence():
    w = _world()
    w.tick(10)
    snap = w.snapshot()
    fork = w.fork()
    w.tick(10)
    after = w.bus.copy()
    fork.set("g.k", -1.0)  # the fork is independent
    fork.tick(10)
    assert not np.array_equal(fork.bus, after)
    w.restore(snap)
    assert w.tick_count == 10
    w.tick(10)
    assert np.array_equal(w.bus, after)
    twin = w.fork()
    twin.tick(5)
    w.tick(5)
    assert np.array_equal(twin.bus, w.bus)  # same seed state, same inputs, same result
    for world in (w, fork, twin):
        world.close()


def test_observers_see_ticks_rollbacks_and_events():
    seen = {"ticks": 0, "rollbacks": [], "events": []}

    class Obs(Observer):
        def on_tick(self, view):
            seen["ticks"] += 1

        def on_rollback(self, view, from_tick):
            seen["rollbacks"].append((from_tick, view.tick))

        def on_event(self, view, event):
            seen["events"].append(event.kind)

    w = _world()
    w.observe(Obs())
    w.tick(5)
    w.backtick(2)
    w.set("g.k", 2.0)
    w.add_module(Counter("c"))
    assert seen["ticks"] == 5 and seen["rollbacks"] == [(5, 3)]
    assert seen["events"] == ["param", "module_added"]


def test_thread_with_concurrent_calls():
    w = _world()
    w.start()
    errors: list[BaseException] = []

    def brain(k: int) -> None:
        try:
            for j in range(30):
                w.get("g.y")
                w.set("g.k", float(j))
                with w.lock():
                    t = w.tick_count
                    w.tick(2)
                    assert w.tick_count == t + 2
                if j % 10 == 0:
                    # Another brain's backtick may undo this brain's add_module (rollback restores
                    # structure), so a sequence that must hold together runs under the lock.
                    with w.lock():
                        w.backtick(1)
                        w.add_module(Counter(f"c{k}_{j}"))
                        w.remove_module(f"c{k}_{j}")
                    w.backtick(1)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=brain, args=(k,)) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    w.stop()
    assert not errors
    assert not w.running and w.tick_count > 0
    w.tick(3)  # usable after stop
    w.close()


def test_thread_error_surfaces_on_stop():
    w = World(step="1ms")
    w.add_module(Boom("bomb", at_tick=20))
    w.start()
    assert w.wait(5.0)  # the loop ends by itself on the error
    with pytest.raises(ModuleError, match="bomb"):
        w.stop()
    assert w.tick_count == 20


def test_start_until_and_realtime():
    w = _world()
    w.start(realtime=20.0, until=0.05)  # 50 ms simulated at 20x real time
    assert w.wait(10.0)
    w.stop()
    assert w.tick_count == 50


@pytest.mark.parametrize("factory", [
    lambda: Sine("s", frequency="3Hz"), lambda: Gain("g", n=3, k=2.0), lambda: Integrator("i", n=2),
    lambda: Noise("n", n=4), lambda: Counter("c"),
])
def test_check_module_on_basic_modules(factory):
    report = check_module(factory())
    report.assert_ok()
    assert "step -> restore -> step" in report.checked


def test_check_module_finds_a_module_that_forgets_state():
    class Leaky(Module):
        def outputs(self):
            return (Port("y", ()),)

        def start(self, t_ns):
            self.x = 0.0

        def step(self, t_ns, dt_ns):
            self.x += 1.0
            self.out["y"][...] = self.x

    report = check_module(Leaky("leaky"))
    assert not report.ok and any("replay" in p for p in report.problems)


def test_check_module_finds_a_module_that_says_its_steps_leave_its_state_alone_and_changes_it():
    class Liar(Latch):
        def steps_change_state(self):
            return False

    assert check_module(Latch("honest", hold=False)).ok and check_module(Latch("held")).ok
    report = check_module(Liar("liar", hold=False))
    assert any("steps_change_state() said False, and the step at tick" in p for p in report.problems), report


def test_events_say_whether_the_scenario_or_a_caller_made_them():
    kinds = []

    class Obs(Observer):
        def on_event(self, view, event):
            kinds.append((event.kind, event.source, event.tick))

    w = World(step="1ms")
    w.add_module(Gain("g"))
    w.observe(Obs())
    w.at("2ms", "set gain", lambda world: world.set("g.k", 5.0))
    w.tick(3)
    w.set("g.k", 1.0)
    assert kinds == [("param", "scenario", 2), ("param", "api", 3)]


def test_ports_begin_at_their_start_values():
    class Biased(Module):
        def inputs(self):
            return (Port("u", (2,), start=(1.0, -1.0)), Port("k", (), start=3.0))

        def outputs(self):
            return (Port("y", (2,)),)

        def step(self, t_ns, dt_ns):
            self.out["y"][...] = self.inp["u"] * self.inp["k"]

    w = World(step="1ms")
    w.add_module(Biased("b"))
    w.tick()
    assert list(w.get("b.y")) == [3.0, -3.0]
    w.set("b.k", 0.5)
    w.add_module(Counter("c"))  # a new structure keeps the values the ports have now
    w.tick()
    assert list(w.get("b.y")) == [0.5, -0.5]


class Mixer(Module):
    """Reads its inputs and writes its outputs through the flat views (with a block port and a view)."""

    def inputs(self):
        return (Port("a", (1,)), Port("b", (2,)))

    def outputs(self):
        return (Port("sum", ()), Port("rows", (2, 2)), Port("row1", (2,), view_of=("rows", 1)), Port("last", ()))

    def step(self, t_ns, dt_ns):
        a, b0, b1 = self.inp_flat.tolist()
        self.out_flat[:] = (a + b0 + b1, a, b0, b1, a * 2, t_ns * 1e-9)


def test_flat_port_views_follow_declaration_order_and_survive_rebinding_and_fork():
    w = World(step="1ms")
    w.add_module(Constant("k", value=[3.0]))
    w.add_module(Mixer("m"), connect=[("k.y", "m.a")])
    w.set("m.b", [1.0, 2.0])
    w.tick(2)
    assert w.get("m.sum") == 6.0 and w.get("m.last") == pytest.approx(1e-3)
    assert np.array_equal(w.get("m.rows"), [[3.0, 1.0], [2.0, 6.0]]) and np.array_equal(w.get("m.row1"), [2.0, 6.0])
    mixer = w.modules["m"]
    assert mixer.out_flat.size == 6 and mixer.inp_flat.size == 3  # views are not counted twice
    with pytest.raises(ValueError):
        mixer.inp_flat[0] = 1.0  # inputs are read-only, as in `inp`
    w.add_module(Counter("c"))  # a new structure: the flat views are bound again, to the new bus
    w.set("m.b", [0.0, 0.0])
    w.tick()
    assert w.get("m.sum") == 3.0
    f = w.fork()
    f.set("m.b", [1.0, 1.0])
    f.tick()
    assert f.get("m.sum") == 5.0 and w.get("m.sum") == 3.0  # the fork writes its own bus
    f.close()
    w.close()


class Runs(Module):
    """A one-dimensional block with views of element runs of it."""

    def __init__(self, name, views, **kw):
        super().__init__(name, **kw)
        self.views = views

    def outputs(self):
        return (Port("data", (6,)), *(Port(n, shape, view_of=("data", at)) for n, shape, at in self.views))

    def step(self, t_ns, dt_ns):
        self.out_flat[:] = range(6)


def test_a_view_of_a_one_dimensional_block_is_a_run_of_its_elements():
    w = World(step="1ms")
    w.add_module(Runs("r", [("one", (), 5), ("pair", (2,), 1), ("four", (4,), 2)]))
    w.tick()
    assert w.get("r.one") == 5.0 and w.get("r.pair").tolist() == [1.0, 2.0] and w.get("r.four").tolist() == [2, 3, 4, 5]
    for bad in [("late", (2,), 5), ("before", (), -1)]:
        with pytest.raises(WiringError, match=rf"port {bad[0]!r} of shape .* does not fit 'data' \(6,\) from element"):
            w.add_module(Runs("bad", [bad]))
    assert list(w.modules) == ["r"]


def test_worlds_step_the_way_the_module_run_asks(tick_runner):
    w = World(step="1ms")
    w.add_module(Counter("c"))
    w.tick(2)
    assert w.compiled is tick_runner and w.fork().compiled is tick_runner
