"""History with keyframes (`World(keyframe_every=k)`): a state every k ticks and after each edit or
event, the ticks between stepped again from the keyframe before them. Random sequences of ticks,
backticks, edits, parameters and events leave such a world bit for bit where a world with a state
every tick is; a failed tick rolls back as exactly; events never run twice; a step that does not
repeat itself is reported; a module that cannot roll back keeps a state every tick. And the hot path's
history entries (the bus as bytes) come back as the states they were. Both ways: the generated tick
and the plain loop (`tick_runner`)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dynabrain.modules.basic import Counter, Gain, Noise, Sine
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator.kernel.core import BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ModuleError, RollbackError
from dynabrain.orchestrator.kernel.module import Capabilities, Module, Port
from dynabrain.orchestrator.kernel.world import World

pytestmark = pytest.mark.usefixtures("tick_runner")


def scene() -> SceneSpec:
    return SceneSpec(bodies=(
        BodySpec("floor", "plane", ()),
        BodySpec("a", "box", (0.1, 0.1, 0.1), pos=(0.0, 0.0, 0.3), mass=0.1),
        BodySpec("b", "sphere", (0.05,), pos=(0.3, 0.0, 0.4), mass=0.05),
    ))


def make_world(every: int, history: int = 40) -> World:
    world = World("kf", step="2ms", seed=5, history=history, core=MujocoCore("core", scene()),
                  keyframe_every=every)
    world.add_module(Noise("noise", n=2, sigma=0.2))
    world.add_module(Gain("g", n=2, k=2.0), connect=[("noise.y", "g.u")])
    world.add_module(Sine("drive", amplitude=0.3, frequency="1.5Hz"))
    return world


def fingerprint(world: World) -> tuple:
    snap = world.snapshot()
    return (snap.tick, tuple(sorted(world.modules)), snap.bus.tobytes(), pickle.dumps((snap.states, snap.params)))


op = st.one_of(
    st.tuples(st.just("tick"), st.integers(1, 9)),
    st.tuples(st.just("backtick"), st.integers(1, 30)),
    st.tuples(st.just("gain"), st.floats(-5, 5)),
    st.tuples(st.just("push"), st.floats(-1, 1)),
    st.tuples(st.just("add"), st.integers(0, 1)),
    st.tuples(st.just("remove"), st.integers(0, 1)),
    st.tuples(st.just("make"), st.sampled_from([["a"], ["a", "b"]])),
    st.tuples(st.just("event"), st.integers(1, 12)),
    st.tuples(st.just("drive"), st.lists(st.floats(-1, 1), min_size=1, max_size=7)),
)


def apply(world: World, action: tuple, fired: list) -> None:
    kind, arg = action
    if kind == "tick":
        world.tick(arg)
    elif kind == "backtick":
        world.backtick(min(arg, world.history.available))
    elif kind == "gain":
        world.set("g.k", arg)
    elif kind == "push":
        world.set("core.a.wrench", [arg, 0.0, 0.0, 0.0, 0.0, 0.0])
    elif kind == "drive":  # an input written before each tick (`World.run`)
        wrench = np.zeros((len(arg), 6))
        wrench[:, 1] = arg
        world.run(len(arg), inputs={"core.a.wrench": wrench})
    elif kind == "add" and f"c{arg}" not in world.modules:
        world.add_module(Counter(f"c{arg}"))
    elif kind == "remove" and f"c{arg}" in world.modules:
        world.remove_module(f"c{arg}")
    elif kind == "make":
        world.make(arg)
    elif kind == "event":  # an action a few ticks ahead that changes a parameter and counts its runs
        tick = world.tick_count + arg

        def action(w: World, tick: int = tick) -> None:
            fired.append(tick)
            w.set("drive.amplitude", 0.01 * (tick % 7))

        world.at(tick * world.dt_ns, f"e{tick}", action)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(2, 7), st.lists(op, min_size=3, max_size=14))
def test_keyframes_step_to_the_same_bits_as_a_state_every_tick(every, ops):
    ops = [("tick", 5), *ops, ("tick", 3), ("backtick", 9), ("tick", 2)]
    every_tick, keyframes = make_world(1), make_world(every)
    fired_a: list = []
    fired_b: list = []
    for i, action in enumerate(ops):
        if action[0] == "backtick":  # both as far back: as far as the world with a state every tick can go
            action = ("backtick", min(action[1], every_tick.history.available))
        apply(every_tick, action, fired_a)
        apply(keyframes, action, fired_b)
        assert fingerprint(keyframes) == fingerprint(every_tick), f"diverged at op {i}: {action}"
        # never less; after a backtick it can be more: the keyframe ring still holds the keyframe before
        # the oldest tick within its depth, which a ring of a state every tick has dropped
        assert keyframes.history.available >= every_tick.history.available
    assert fired_a == fired_b  # events ran as often: never again while stepping from a keyframe
    for w in (every_tick, keyframes):
        w.close()


def test_a_deep_backtick_steps_again_from_the_keyframe_before_it():
    every_tick, keyframes = make_world(1, history=100), make_world(8, history=100)
    for w in (every_tick, keyframes):
        w.tick(250)
    assert keyframes.history.available == every_tick.history.available == 100
    for n in (1, 7, 8, 9, 63, 100):
        for w in (every_tick, keyframes):
            w.backtick(n)
        assert fingerprint(keyframes) == fingerprint(every_tick), n
        for w in (every_tick, keyframes):
            w.tick(n)
        assert fingerprint(keyframes) == fingerprint(every_tick), n
    with pytest.raises(RollbackError, match="goes beyond the history"):
        keyframes.backtick(101)
    assert "keyframes every 8 ticks" in keyframes.history.describe()
    assert keyframes.history.states_when_full == 14 and every_tick.history.states_when_full == 101
    for w in (every_tick, keyframes):
        w.close()


@pytest.mark.parametrize("how", ["run", "set"])
def test_inputs_written_every_tick_keep_keyframes_and_step_again_to_the_same_bits(how):
    """A brain that writes an input before every tick (`run` with inputs, or `set` then `tick`) leaves
    history holding keyframes only: the ticks between hold the inputs, and a backtick to any of them
    writes them again on the way (the same bits as a world with a state every tick)."""
    worlds = [make_world(1), make_world(4)]
    pushes = np.zeros((30, 6))
    pushes[:, 0] = np.sin(np.arange(30) * 0.7) * 0.5
    pushes[:, 2] = np.cos(np.arange(30) * 0.3)
    for w in worlds:
        w.tick(3)
        if how == "run":
            w.run(30, inputs={"core.a.wrench": pushes})
        else:
            for row in pushes:
                w.set("core.a.wrench", row)
                w.tick()
        w.set("core.a.wrench", [0.0, 0.0, 0.3, 0.0, 0.0, 0.0])  # written at the newest tick, not stepped yet
    every_tick, keyframes = worlds
    assert fingerprint(keyframes) == fingerprint(every_tick)
    assert keyframes.tick_count == 33
    assert keyframes.history.describe().startswith("9 of")  # ticks 0, 4, ..., 32: keyframes only
    for n in (0, 1, 2, 3, 5, 6, 7):
        for w in worlds:
            w.backtick(n)
        assert fingerprint(keyframes) == fingerprint(every_tick), n
        np.testing.assert_array_equal(keyframes.get("core.a.wrench"), every_tick.get("core.a.wrench"))
        for w in worlds:
            w.tick(1)
        assert fingerprint(keyframes) == fingerprint(every_tick), n
    for w in worlds:
        w.close()


class Boom(Module):
    """Counts its steps; its step raises at ``at_tick``."""

    def __init__(self, name: str, at_tick: int):
        super().__init__(name)
        self.at_tick = at_tick

    def outputs(self):
        return (Port("count", ()),)

    def start(self, t_ns):
        self.count = 0

    def step(self, t_ns, dt_ns):
        if t_ns // dt_ns == self.at_tick:
            raise ValueError("boom")
        self.count += 1
        self.out["count"][...] = self.count

    def get_state(self):
        return self.count

    def set_state(self, state):
        self.count = state


def test_a_failed_tick_rolls_back_as_exactly():
    worlds = []
    for every in (1, 5):
        w = make_world(every)
        w.add_module(Boom("boom", at_tick=13))
        with pytest.raises(ModuleError, match="boom") as err:
            w.tick(20)
        assert err.value.tick == 13 and w.tick_count == 13
        worlds.append(w)
    assert fingerprint(worlds[0]) == fingerprint(worlds[1])
    for w in worlds:
        w.close()


class Once(Counter):
    """A counter that refuses to step a tick it has stepped before (what it remembers is no state)."""

    def start(self, t_ns):
        super().start(t_ns)
        self.seen: set[int] = set()

    def step(self, t_ns, dt_ns):
        if t_ns in self.seen:
            raise RuntimeError("stepped twice")
        self.seen.add(t_ns)
        super().step(t_ns, dt_ns)


def test_a_step_that_does_not_repeat_itself_is_reported_and_the_world_left_at_the_keyframe():
    w = World(step="1ms", keyframe_every=4)
    w.add_module(Once("once"))
    w.tick(11)
    with pytest.raises(RollbackError, match="from the keyframe at tick 8 to tick 10 failed at tick 8"):
        w.backtick(1)
    assert w.tick_count == 8 and w.get("once.count") == 8 and w.history.available == 8
    w.close()


class Unsaved(Counter):
    CAPABILITIES = Capabilities(can_rollback=False)


def test_a_module_that_cannot_roll_back_keeps_a_state_every_tick():
    w = World(step="1ms", keyframe_every=4)
    w.add_module(Counter("c"))
    w.add_module(Unsaved("u"))
    w.tick(10)
    assert all(type(e) is tuple for e in w.history._ring)  # nothing to step again
    with pytest.raises(RollbackError, match="cannot roll back"):
        w.backtick(1)
    w.close()


def test_keyframes_are_a_whole_number():
    for bad in (0, -2, 1.5, True):
        with pytest.raises(DynabrainError, match="keyframes every"):
            World(keyframe_every=bad)
    assert World(keyframe_every=3).fork().history.every == 3


def test_history_holds_the_bus_as_bytes_and_gives_states_back():
    w = make_world(1)
    w.tick(12)
    entry = w.history._ring[-1]
    assert type(entry[3]) is bytes  # the hot path's copy
    top = w.history.top
    assert np.array_equal(top.bus.view(np.int64), w.bus.view(np.int64)) and not top.bus.flags.writeable
    assert top.tick == 12 and top.states == tuple(entry[6:])
    before = fingerprint(w)
    w.tick(5)
    w.backtick(5)
    assert fingerprint(w) == before
    snap = w.snapshot()  # snapshots keep an array of their own
    assert isinstance(snap.bus, np.ndarray) and snap.bus.flags.writeable
    w.close()


class Scalar(Module):
    """One scalar output: 1/u, so u = 0 makes it infinite (a span of one value: summed in the tick itself)."""

    def inputs(self):
        return (Port("u", (), start=1.0),)

    def outputs(self):
        return (Port("y", ()),)

    def step(self, t_ns, dt_ns):
        u = float(self.inp["u"])
        self.out["y"][...] = float("inf") if u == 0.0 else 1.0 / u


def test_a_short_span_is_checked_in_the_generated_tick():
    w = World(step="1ms")
    w.add_module(Scalar("s"))
    if w.compiled:
        source = w.structure.compiled.source
        assert "mv[" in source and "search_outputs(buf, n)" in source and "add_span" not in source
    w.tick(3)
    w.set("s.u", 0.0)
    with pytest.raises(ModuleError, match="output 'y' is inf") as err:
        w.tick()
    assert (err.value.module, err.value.tick, w.tick_count) == ("s", 3, 3)
    w.close()


def test_history_says_how_many_states_it_keeps_when_a_module_cannot_roll_back():
    from dynabrain.orchestrator.kernel.module import Capabilities, Module

    class OneWay(Module):
        CAPABILITIES = Capabilities(can_rollback=False)

    w = World(history=100)
    w.add_module(OneWay("once"))
    w.tick(150)
    text = w.history.describe()
    assert text.startswith("102 of 102 states (a whole state every tick"), text
    w.close()
    plain = World(history=100)
    plain.tick(150)
    assert plain.history.describe().startswith("51 of 52 states (keyframes every 2 ticks)"), plain.history.describe()
    plain.close()
