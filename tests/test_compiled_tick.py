"""The tick two ways: the generated function (`CompiledTick`) and the plain loop (`PlainTick`) step the
same worlds to bit-identical states, tick by tick; the generated source is named after what it holds,
shows in tracebacks and in `inspect`, and leaves `linecache` with the code it belongs to."""

from __future__ import annotations

import gc
import inspect
import linecache
import math
import pickle
import traceback
from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.basic import Counter, Gain, Integrator, Noise
from dynabrain.orchestrator.kernel.errors import DynabrainError, ModuleError
from dynabrain.orchestrator.kernel.module import Module, Port
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario import load_world

HUMANOID = Path(__file__).resolve().parent.parent / "scenarios" / "humanoid_stand.yaml"
BOTH = pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "plain"])


class Fan(Module):
    """Ten scalar inputs and outputs: each output from its input, the time and the module's step count.
    Ten connections in a scrambled order are more runs than the kernel copies one by one, so they go
    as one pair of index arrays (the "gather" copies)."""

    N = 10

    def inputs(self):
        return tuple(Port(f"u{i}", ()) for i in range(self.N))

    def outputs(self):
        return tuple(Port(f"y{i}", ()) for i in range(self.N))

    def start(self, t_ns):
        self.count = 0

    def step(self, t_ns, dt_ns):
        self.count += 1
        for i in range(self.N):
            self.out[f"y{i}"][...] = 0.5 * self.inp[f"u{i}"] + math.sin(1e-9 * t_ns * (i + 1)) + 1e-3 * self.count

    def get_state(self):
        return self.count

    def set_state(self, state):
        self.count = state


class Boom(Module):
    def step(self, t_ns, dt_ns):
        if t_ns >= 3_000_000:
            raise ValueError("boom")


def record(world: World, ticks: int, frames: list) -> None:
    """Step ``ticks`` ticks; after each, the bus (as int64, bit for bit) and every module's saved state."""
    for _ in range(ticks):
        world.tick()
        top = world.history.top if world.history.every == 1 else world.snapshot()  # keyframes: a capture now
        assert np.array_equal(top.bus.view(np.int64), world.bus.view(np.int64))  # (the bus may hold NaN)
        frames.append((top.tick, top.bus.view(np.int64).copy(), pickle.dumps((top.states, top.params))))


def chain(compiled: bool) -> tuple[World, list]:
    """A chain of state modules (delayed connections) and feedthrough fans (direct ones, scrambled),
    with periods of 1, 2 and 3 ms, a module that joins late (its own phase), edits and rollbacks."""
    w = World("chain", step="1ms", seed=11, history=40, compiled=compiled, keyframe_every=1)  # `record` reads each
    w.add_module(Noise("noise", n=3, sigma=0.3))
    w.add_module(Integrator("int", n=3), period="2ms", connect=[("noise.y", "int.u")])
    w.add_module(Gain("gain-1", n=3, k=1.7), connect=[("int.y", "gain-1.u")])
    w.add_module(Fan("fan-a"))
    w.add_module(Fan("fan_b"), connect=[(f"fan-a.y{i}", f"fan_b.u{Fan.N - 1 - i}") for i in range(Fan.N)])
    w.add_module(Fan("3fan"), period="3ms")
    for i in range(Fan.N):
        w.connect(f"fan_b.y{i}", f"3fan.u{(3 * i) % Fan.N}", delay=True)
    for i in range(5):
        w.connect(f"3fan.y{i}", f"fan-a.u{2 * i}")
    s = w.structure
    assert s.delayed_gather and any(e.gather for e in s.dispatch) and any(e.copies for e in s.dispatch)
    assert w.schedule_order() == ["noise", "int", "gain-1", "3fan", "fan-a", "fan_b"]
    frames: list = []
    record(w, 5, frames)
    w.set("gain-1.k", -0.4)
    w.add_module(Counter("late"), period="3ms")  # joins at tick 5: due at 5, 8, 11, ...
    record(w, 10, frames)
    w.backtick(4)
    w.set("noise.sigma", 2.0)
    record(w, 6, frames)
    w.remove_module("int")
    w.connect("noise.y", "gain-1.u", delay=True)
    record(w, 7, frames)
    fork = w.fork()
    record(fork, 8, frames)
    record(w, 3, frames)
    fork.close()
    return w, frames


def same(a: list, b: list) -> None:
    assert len(a) == len(b)
    for (tick, bus, states), (tick2, bus2, states2) in zip(a, b, strict=True):
        assert tick == tick2
        assert np.array_equal(bus, bus2), f"bus differs at tick {tick}"
        assert states == states2, f"module states differ at tick {tick}"


def test_a_chain_steps_to_the_same_bits_both_ways():
    w1, generated = chain(compiled=True)
    w2, plain = chain(compiled=False)
    assert w1.compiled and not w2.compiled
    same(generated, plain)
    assert np.array_equal(w1.bus.view(np.int64), w2.bus.view(np.int64))
    for w in (w1, w2):
        w.close()


def test_the_humanoid_steps_to_the_same_bits_both_ways(monkeypatch):
    runs = []
    for flag in ("1", "0"):  # load_world makes its World without compiled=: the environment decides
        monkeypatch.setenv("DYNABRAIN_COMPILED", flag)
        world = load_world(HUMANOID)
        assert world.compiled is (flag == "1")
        frames: list = []
        record(world, 150, frames)
        world.backtick(40)
        record(world, 90, frames)
        world.close()
        runs.append(frames)
    same(*runs)
    assert len({bus.tobytes() for _tick, bus, _states in runs[0]}) > 100  # it moved


@BOTH
def test_a_failing_module_is_named_from_its_tick(compiled):
    w = World(step="1ms", compiled=compiled)
    w.add_module(Counter("c"))
    w.add_module(Boom("servo-1"), period="2ms")
    w.add_module(Counter("after"))
    with pytest.raises(ModuleError) as err:
        w.tick(10)
    assert (err.value.module, err.value.tick, w.tick_count) == ("servo-1", 4, 4)
    w.close()


def test_a_traceback_shows_the_generated_line_and_the_source_goes_with_the_world():
    w = World(step="1ms", compiled=True)
    w.add_module(Counter("c"))
    w.add_module(Boom("servo-1"))
    tick = w.structure.compiled
    filename = tick.filename
    assert filename.startswith("<dynabrain tick ") and linecache.getlines(filename)
    with pytest.raises(ModuleError) as err:
        w.tick(10)
    text = "".join(traceback.format_exception(err.value))
    lines = tick.source.splitlines()
    call = next(i for i, line in enumerate(lines, 1) if "step_servo_1(" in line)
    assert f'File "{filename}", line {call}, in tick\n    step_servo_1(t_ns, 1000000)\n' in text
    linecache.checkcache()  # the entry has no file behind it: checkcache leaves it
    assert inspect.getsource(tick.run) == tick.source  # what pdb's list shows
    del err, tick, text
    w.close()
    del w
    gc.collect()
    assert filename not in linecache.cache


def test_locals_are_named_after_the_modules():
    w = World(step="1ms", compiled=True)
    w.add_module(Integrator("a-b", n=2, x0=1.5))
    w.add_module(Gain("a_b", n=2), connect=[("a-b.y", "a_b.u")])  # delayed: the integrator has state
    w.add_module(Gain("1x", n=2), connect=[("a_b.y", "1x.u")])  # direct
    w.add_module(Gain("x", n=2), connect=[("1x.y", "x.u")])
    source = w.structure.compiled.source
    for name in ("step_a_b=", "step_a_b_2=", "step_1x=", "step_x=", "delayed_dst=", "delayed_src=",
                 "_1x_in_dst=", "_1x_in_src=", "x_in_dst=", "x_in_src="):
        assert name in source, (name, source)
    assert "k0" not in source and "s0(" not in source
    w.tick(3)  # the integrator's state feeds the chain: every step runs
    assert np.all(w.get("x.y") != 0.0)
    w.close()


def test_the_state_savers_source_is_registered():
    w = World(step="1ms")
    w.add_module(Counter("c"))
    w.add_module(Latchless("held"))
    w.tick()
    name = w.parts.context.save_states.__code__.co_filename
    assert name.startswith("<dynabrain state saver ") and "def save(" in "".join(linecache.getlines(name))
    w.close()


class Latchless(Module):
    """A module whose steps leave its (non-empty) state alone: the saver holds its state as a value."""

    def get_state(self):
        return "fixed"

    def set_state(self, state):
        pass

    def steps_change_state(self):
        return False


def test_the_environment_switch_and_fork(monkeypatch):
    monkeypatch.setenv("DYNABRAIN_COMPILED", "0")
    plain = World()
    assert not plain.compiled and not plain.fork().compiled
    assert World(compiled=True).compiled  # the keyword wins over the environment
    monkeypatch.setenv("DYNABRAIN_COMPILED", "off")
    assert not World().compiled
    monkeypatch.delenv("DYNABRAIN_COMPILED")
    assert World().compiled and not World(compiled=False).fork().compiled
    monkeypatch.setenv("DYNABRAIN_COMPILED", "sometimes")
    with pytest.raises(DynabrainError, match="DYNABRAIN_COMPILED='sometimes'"):
        World()
