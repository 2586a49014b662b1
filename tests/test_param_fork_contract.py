"""Parameters and fork in the module contract: parameters are read-only values that a change replaces
(history and forks share them), a rollback brings back a parameter set after it, and a module that
overrides `Module.fork` is copied by it, also when another module holds it."""

from __future__ import annotations

import pytest

from dynabrain.modules.basic import Gain
from dynabrain.orchestrator import World
from dynabrain.orchestrator.kernel.module import Module, ParamValues


class Holder(Module):
    """Holds another module (as a sensor holds the core)."""

    def __init__(self, name, other, **params):
        super().__init__(name, **params)
        self.other = other


class Forked(Gain):
    forks = 0

    def fork(self, memo):
        Forked.forks += 1
        twin = Forked(self.name, k=self.params["k"])
        twin.adopt_param_state(self.param_state())
        memo[id(self)] = twin
        return twin


def test_parameters_are_read_only_values_replaced_on_a_change_and_rolled_back():
    w = World()
    g = Gain("g", k=2.0)
    w.add_module(g)
    before = g.params
    assert isinstance(before, ParamValues) and before["k"] == 2.0
    with pytest.raises(TypeError, match="read-only"):
        g.params["k"] = 3.0
    w.tick(2)
    w.set("g.k", 5.0)
    assert g.params is not before and before["k"] == 2.0 and g.params["k"] == 5.0
    w.tick(3)
    w.backtick(4)  # to before the change
    assert g.params is before
    w.close()


def test_a_module_that_overrides_fork_is_copied_by_it_also_where_another_holds_it():
    Forked.forks = 0
    w = World()
    f = Forked("f", k=3.0)
    w.add_module(Holder("h", f))  # the holder comes first: its copy copies f through f's own fork
    w.add_module(f)
    other = w.fork()
    twin, holder = other.modules["f"], other.modules["h"]
    assert Forked.forks == 1 and twin is not f and holder.other is twin
    assert twin.params is f.params  # shared: never changed in place
    w.close()
    other.close()
