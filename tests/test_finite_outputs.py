"""Non-finite outputs are found at the tick they appear: the tick fails and is rolled back, naming the
module, the port and the tick; a module that means NaN opts out (`Capabilities.finite_outputs`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dynabrain.orchestrator.kernel.errors import NonFiniteOutputError
from dynabrain.orchestrator.kernel.finite import SMALL
from dynabrain.orchestrator.kernel.module import Capabilities, Module, Port
from dynabrain.orchestrator.kernel.world import World

pytestmark = pytest.mark.usefixtures("tick_runner")  # the generated tick and the plain loop alike


class Divide(Module):
    """``y = 1 / u`` (element by element) and ``count`` of steps: a zero in ``u`` gives an infinity."""

    def __init__(self, name: str, n: int = 3, **kw):
        self.n = n
        super().__init__(name, **kw)
        self.count = 0

    def inputs(self):
        return (Port("u", (self.n,), start=(1.0,) * self.n), Port("spare", doc="read by nobody"))

    def outputs(self):
        return (Port("y", (self.n,)), Port("count"))

    def step(self, t_ns, dt_ns):
        with np.errstate(divide="ignore", invalid="ignore"):
            self.out["y"][...] = 1.0 / self.inp["u"]
        self.count += 1
        self.out["count"][...] = self.count

    def get_state(self):
        return self.count

    def set_state(self, state):
        self.count = state


class Unset(Module):
    """An input that starts NaN (unset, like a body's velocity) and an output copied from it."""

    CAPABILITIES = Capabilities(finite_outputs=False)

    def inputs(self):
        return (Port("v", (2,), start=(np.nan, np.nan)),)

    def outputs(self):
        return (Port("echo", (2,)),)

    def step(self, t_ns, dt_ns):
        self.out["echo"][...] = self.inp["v"]


def test_an_infinite_output_fails_its_tick_naming_module_port_and_tick():
    with World(step="1ms") as w:
        w.add_module(Divide("a"))
        w.add_module(Divide("b"), connect=[("a.y", "b.u")])
        w.tick(5)
        before = w.get("a.y").copy()
        w.set("a.u", [1.0, 0.0, 4.0])
        with pytest.raises(NonFiniteOutputError) as err:
            w.tick()
        e = err.value
        assert (e.module, e.port, e.tick) == ("a", "y", 5)
        assert "output 'y' is inf (element 2 of 3" in str(e) and "at tick 5" in str(e)
        assert w.tick_count == 5 and w.error is e and w.modules["a"].count == 5  # rolled back, state too
        assert np.array_equal(w.get("a.y"), before)
        w.set("a.u", [1.0, 2.0, 4.0])
        w.tick()
        assert w.get("b.y") == pytest.approx([1.0, 2.0, 4.0])


def test_an_opted_out_module_outputs_nan_and_its_readers_are_checked():
    with World(step="1ms") as w:
        w.add_module(Unset("src"))
        w.add_module(Divide("b", n=2))
        w.tick(3)  # an unset input and an opted-out output: nothing to report
        w.connect("src.echo", "b.u")
        with pytest.raises(NonFiniteOutputError, match=r"module 'b': step\(\) at tick 3 failed: output 'y' is NaN"):
            w.tick()
        w.set("src.v", [2.0, 4.0])
        w.tick()
        assert w.get("b.y") == pytest.approx([0.5, 0.25])


def test_one_module_opts_out_by_its_capabilities():
    with World(step="1ms") as w:
        m = Divide("a")
        m.CAPABILITIES = dataclasses.replace(m.CAPABILITIES, finite_outputs=False)
        w.add_module(m)
        w.set("a.u", [0.0, 0.0, 0.0])
        w.tick(3)
        assert np.isinf(w.get("a.y")).all()


def test_spans_merge_across_finite_inputs_and_stop_at_what_may_be_nan():
    with World(step="1ms") as w:
        w.add_module(Divide("a"))
        w.add_module(Divide("b"), connect=[("a.y", "b.u")])
        w.add_module(Unset("src"))
        w.add_module(Divide("c", n=2), connect=[("src.echo", "c.u")])
        slots = w.structure.layout.slots
        # b's inputs lie between a's outputs and its own, and hold finite values: one span; src's input
        # starts NaN, its outputs are not checked, and c reads them: c's outputs make a span of their own
        assert w.structure.output_check.spans == ((slots["a.y"].start, slots["b.count"].start + 1),
                                                   (slots["c.y"].start, slots["c.count"].start + 1))


def test_a_long_span_is_checked_too():
    with World(step="1ms") as w:
        w.add_module(Divide("big", n=4 * SMALL))
        w.tick()
        u = np.ones(4 * SMALL)
        u[-1] = 0.0
        w.set("big.u", u)
        with pytest.raises(NonFiniteOutputError, match=rf"output 'y' is inf \(element {4 * SMALL} of {4 * SMALL}"):
            w.tick()
        assert w.tick_count == 1


def test_nan_written_by_hand_into_an_input_inside_a_span_is_no_failure():
    with World(step="1ms") as w:
        w.add_module(Divide("a"))
        w.add_module(Divide("b"))
        w.tick()
        w.set("b.spare", np.nan)  # between a's outputs and b's, read by nobody
        w.tick(2)  # the sum is not finite; the search finds every output finite, and the ticks go on
        w.set("b.u", [np.nan, 1.0, 1.0])  # ... but b passes this one on
        with pytest.raises(NonFiniteOutputError, match=r"module 'b'.*output 'y' is NaN \(element 1 of 3"):
            w.tick()
        assert w.tick_count == 3


def test_multi_rate_modules_are_checked_at_their_own_ticks():
    with World(step="1ms") as w:
        w.add_module(Divide("slow"), period="3ms")
        w.tick(2)
        w.set("slow.u", [0.0, 1.0, 1.0])
        w.tick()  # tick 2: slow is not due; its outputs stay finite
        with pytest.raises(NonFiniteOutputError) as err:
            w.tick()
        assert err.value.tick == 3 and err.value.module == "slow"
