"""The contracts are explicit: the module and core base classes are abstract base classes whose
abstract methods are enforced, optional hooks are declared methods with defaults, ports are bound
through `Module.bind_ports` and a `PortBinding`, parameter changes belong to the world a module is in,
the MuJoCo core hands its model and data out through `MujocoCore.mj`, and a core's structural edits
are named, immutable values. Physics runs for real (MuJoCo stepping), no fakes."""

from __future__ import annotations

import copy
import dataclasses
import pickle
from collections.abc import Sequence

import numpy as np
import pytest

from dynabrain.modules.basic import Counter
from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.compiled import MujocoView
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.mujoco.scene import FrozenBody, FrozenObject
from dynabrain.orchestrator.kernel.core import (
    NO_EDITS,
    BodyInfo,
    BodySpec,
    Edits,
    JointSpec,
    PhysicsCore,
    SceneSpec,
    Weld,
)
from dynabrain.orchestrator.kernel.edited import EditedCore
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.module import NO_PORTS, Module, Param, Port, PortBinding
from dynabrain.orchestrator.kernel.world import World, module_spec


def scene() -> SceneSpec:
    """A floor, two boxes falling onto it and a hinged arm."""
    return SceneSpec(bodies=(
        BodySpec("floor", "plane", ()),
        BodySpec("a", "box", (0.1, 0.1, 0.1), pos=(0.0, 0.0, 0.3), mass=0.1),
        BodySpec("b", "box", (0.1, 0.1, 0.1), pos=(0.4, 0.0, 0.5), quat=(0.96, 0.2, 0.1, 0.17), mass=0.1),
        BodySpec("arm", "capsule", (0.02, 0.4), pos=(1.0, 0.0, 1.0),
                 joint=JointSpec("hinge", axis=(0, 1, 0), anchor=(0, 0, 0.2), damping=0.01)),
    ))


class Steady(Module):
    """Outputs its ``gain`` parameter; its steps leave its state alone, so history takes its state once
    per stretch: ``saves`` counts how often it is asked."""

    PARAMS = (Param("gain", 1.0, runtime=True),)

    def __init__(self, name: str, **params):
        super().__init__(name, **params)
        self.saves = 0

    def outputs(self) -> Sequence[Port]:
        return (Port("y", ()),)

    def start(self, t_ns: int) -> None:
        self.out["y"][...] = self.params["gain"]

    def step(self, t_ns: int, dt_ns: int) -> None:
        self.out["y"][...] = self.params["gain"]

    def get_state(self) -> float:
        self.saves += 1
        return 0.0

    def steps_change_state(self) -> bool:
        return False


def physics_world(name: str) -> World:
    # a state every tick: these tests read history's newest entry and count the states saved per tick
    world = World(name, step="2ms", history=200, core=MujocoCore("core", scene()), keyframe_every=1)
    world.add_module(Steady("steady"))
    return world


def poses(world: World) -> np.ndarray:
    return np.concatenate([world.get("core.body_pos").ravel(), world.get("core.body_quat").ravel()])


def run(world: World, ticks: int) -> list[np.ndarray]:
    """The body poses after each of ``ticks`` ticks."""
    out = []
    for _ in range(ticks):
        world.tick()
        out.append(poses(world))
    return out


# -- abstract base classes -------------------------------------------------------------------------------
class HalfCore(PhysicsCore):
    """Answers the scene queries and nothing else: no structural edits, no `place`."""

    def objects(self) -> list[str]:
        return []

    def bodies(self) -> list[str]:
        return []

    def joints(self) -> list[str]:
        return []

    def body_info(self, name: str) -> BodyInfo:
        raise KeyError(name)

    def body_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        raise KeyError(name)

    def body_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        raise KeyError(name)


def test_a_core_missing_an_abstract_method_cannot_be_made():
    with pytest.raises(TypeError, match="abstract") as err:
        HalfCore("core", SceneSpec())
    for missing in ("make", "make_joint", "no_collision", "place", "remove_joint", "selection"):
        assert missing in str(err.value)


def test_an_edited_core_missing_its_engine_hooks_cannot_be_made():
    class NoEngine(EditedCore):
        objects, bodies, joints = HalfCore.objects, HalfCore.bodies, HalfCore.joints
        body_info, body_pose, body_velocity = HalfCore.body_info, HalfCore.body_pose, HalfCore.body_velocity

        def place(self, body, pos, quat=None) -> None:
            raise NotImplementedError

    with pytest.raises(TypeError, match="abstract") as err:
        NoEngine("core", SceneSpec())
    for missing in ("_activate", "_write_all", "_index", "_freeze_entry", "_parent", "_weld_data"):
        assert missing in str(err.value)


def test_modules_have_no_abstract_method_and_their_hooks_have_defaults():
    assert not Module.__abstractmethods__
    m = Module("plain")
    assert m.steps_change_state() and m.get_state() is None
    assert m.scenario_spec() == {"name": "plain", "python": "dynabrain.orchestrator.kernel.module:Module",
                                 "params": {}}
    spec = module_spec(Steady("s", gain=2.0), 2_000_000)  # the world's description uses the hook
    assert spec == {"name": "s", "python": f"{Steady.__module__}:Steady", "params": {"gain": 2.0},
                    "period": "2000000ns"}


def test_place_rewrites_the_core_outputs_through_the_declared_hook():
    with physics_world("w") as world:
        world.tick(3)
        world.place("a", (0.2, 0.3, 0.9))
        assert np.array_equal(world.get("a.pos"), [0.2, 0.3, 0.9])  # on the bus before any step


# -- ports -------------------------------------------------------------------------------------------------
def test_ports_are_bound_and_unbound_through_bind_ports():
    m = Counter("c")
    assert m.binding is None and m.out == {} and m.out_flat is NO_PORTS
    flat = np.zeros(1)
    binding = PortBinding({}, {"count": flat.reshape(())}, out_flat=flat)
    assert m.bind_ports(binding) is None
    assert m.binding is binding and m.out_flat is flat
    m.bind()
    m.start(0)
    m.step(0, 1)
    assert flat[0] == 1
    assert m.bind_ports(None) is binding
    assert m.binding is None and m.inp == {} and m.out == {} and m.inp_flat.size == 0 and m.out_flat.size == 0
    with pytest.raises(DynabrainError, match="bind_ports takes a PortBinding or None, got tuple"):
        m.bind_ports(({}, {}, NO_PORTS, NO_PORTS))


def test_the_world_binds_ports_on_its_bus_and_a_fork_on_its_own():
    calls: list[str] = []

    class Traced(Counter):
        def bind_ports(self, binding):
            calls.append("bind_ports" if binding is not None else "unbind")
            return super().bind_ports(binding)

        def bind(self):
            calls.append("bind")

    with physics_world("w") as world:
        world.add_module(Traced("t"))
        assert calls[0] == "bind_ports" and set(calls[1:]) == {"bind"}  # the ports first, then `bind`
        module = world.modules["t"]
        binding = module.binding
        world.tick(5)
        assert world.get("t.count") == 5 and module.out_flat[0] == 5
        calls.clear()
        fork = world.fork()
        try:
            assert module.binding is binding  # the original is bound again as it was
            twin = fork.modules["t"]
            assert calls[:2] == ["unbind", "bind_ports"] and calls[-1] == "bind"
            assert twin.binding is not binding and not np.shares_memory(twin.out_flat, module.out_flat)
            fork.tick(2)
            assert fork.get("t.count") == 7 and world.get("t.count") == 5
        finally:
            fork.close()


# -- parameters belong to a world ---------------------------------------------------------------------------
def test_two_worlds_keep_their_parameter_changes_apart():
    with physics_world("one") as one, physics_world("two") as two:
        one.tick(20)
        two.tick(20)
        saves, params = two.modules["steady"].saves, two.history.top.params
        snap_one = one.snapshot()
        one.set("core.friction", 0.2)
        one.set("steady.gain", 3.0)
        one.tick(10)
        one.restore(snap_one)  # params back in `one`: another change
        one.tick(10)
        two.tick(10)
        # `two` kept sharing the parameter dicts and the steady state it had: nothing was taken again
        assert two.modules["steady"].saves == saves
        assert two.history.top.params is params
        assert two.get("core.friction") == 1.0 and two.get("steady.gain") == 1.0
        assert one.get("core.friction") == 1.0 and one.get("steady.gain") == 1.0


def test_a_restore_in_one_world_leaves_the_other_worlds_history_exact():
    with physics_world("one") as one, physics_world("two") as two:
        one.tick(10)
        two.tick(10)
        mark = two.snapshot()
        two.set("core.restitution", 0.6)
        expected = run(two, 60)
        start = one.snapshot()
        one.set("core.restitution", 0.3)
        one.tick(30)
        one.backtick(15)
        one.restore(start)
        two.backtick(30)
        assert np.array_equal(poses(two), expected[29])
        assert two.get("core.restitution") == 0.6
        two.restore(mark)
        assert two.get("core.restitution") == 0.0
        two.set("core.restitution", 0.6)
        again = run(two, 60)
        assert all(np.array_equal(a, b) for a, b in zip(again, expected, strict=True))


def test_a_parameter_changed_without_world_set_is_still_recorded_by_its_world():
    with physics_world("w") as world:
        world.tick(10)
        steady = world.modules["steady"]
        version = steady.param_version
        steady.set_param("gain", 5.0)  # not through World.set: the module's binding tells its world
        assert steady.param_version == version + 1
        world.tick(5)
        assert world.get("steady.y") == 5.0 and world.history.top.params[1]["gain"] == 5.0
        world.backtick(5)  # the state of tick 10 was saved before the change
        assert world.get("steady.gain") == 1.0 and steady.param_version == version + 2


# -- the MuJoCo core's view ---------------------------------------------------------------------------------
def test_the_mujoco_view_changes_when_the_core_recompiles():
    with physics_world("w") as world:
        core = world.core
        first = core.mj
        assert isinstance(first, MujocoView) and first.edits == NO_EDITS
        assert first.model.nbody == 5 and first.data.qpos.size == 7 + 7 + 1
        world.tick(20)
        assert core.mj is first  # stepping keeps the compiled model
        world.make(["a", "arm"])  # the state of tick 20 is saved again with this edit
        selected = core.mj
        assert selected is not first and selected.model.nv == 6 + 1  # box a's free joint and the hinge
        assert selected.edits == core.get_state()[0]
        world.tick(10)
        world.make_joint("a", "floor")  # ... and that of tick 30 with this one
        welded = core.mj
        assert welded is not selected and welded.model.neq == 1
        world.tick(10)
        world.backtick(11)  # to tick 29, before the weld: the cached model of the selection again
        assert core.mj is selected
        world.backtick(10)  # to tick 19, before the selection
        assert core.mj is first
        with pytest.raises(dataclasses.FrozenInstanceError):
            core.mj.model = selected.model


def test_a_forked_core_has_a_view_of_its_own():
    with physics_world("w") as world:
        world.make(["a", "b"])
        world.tick(10)
        fork = world.fork()
        try:
            assert fork.core.mj is not world.core.mj and fork.core.mj.data is not world.core.mj.data
            assert fork.core.mj.edits == world.core.mj.edits
            fork.tick(10)
            world.tick(10)
            assert np.array_equal(fork.core.mj.data.qpos, world.core.mj.data.qpos)
        finally:
            fork.close()


# -- structural edits are named values ------------------------------------------------------------------------
def test_edits_are_named_immutable_values_that_pickle_and_compare():
    core = MujocoCore("core", scene())
    assert core.get_state()[0] is NO_EDITS and Edits((), (), ()) == NO_EDITS
    core.make(["a", "b"])
    core.make_joint("a", "b", "glue")
    core.no_collision(["b", "a"])
    edits = core.get_state()[0]
    assert isinstance(edits, Edits)
    assert [type(e) for e in edits.frozen] == [FrozenObject, FrozenObject]
    assert [e.object for e in edits.frozen] == ["floor", "arm"]
    assert isinstance(edits.frozen[1].bodies[0], FrozenBody) and edits.frozen[1].bodies[0].name == "arm"
    weld, = edits.welds
    assert isinstance(weld, Weld) and (weld.name, weld.a, weld.b) == ("glue", "a", "b")
    assert edits.groups == (("a", "b"),)
    assert core.selection == ("a", "b")
    copied = pickle.loads(pickle.dumps(edits))
    assert copied == edits and hash(copied) == hash(edits) and type(copied.welds[0]) is Weld
    assert copy.deepcopy(edits) == edits
    core.remove_joint("glue")
    assert core.get_state()[0].welds == () and core.get_state()[0].frozen == edits.frozen
    core.close()


@pytest.mark.parametrize("engine", ["mujoco", "exudyn"])
def test_an_edited_core_state_is_portable(engine):
    """The edit types are registered state types: a state holding them is exported and imported."""
    make_core = {"mujoco": MujocoCore, "exudyn": ExudynCore}[engine]
    with World("w", step="2ms", core=make_core("core", scene())) as world:
        world.tick(10)
        world.make(["a", "b", "arm"])
        world.make_joint("a", "b", "glue")
        world.no_collision(["a", "arm"])
        world.tick(10)
        data = world.export_state()
        expected = run(world, 20)
        edits = world.core.get_state()[0]
        world.make(["a", "b", "arm", "floor"])  # another structure meanwhile
        world.import_state(data)
        assert world.core.get_state()[0] == edits and world.core.selection == ("a", "b", "arm")
        assert all(np.array_equal(a, b) for a, b in zip(run(world, 20), expected, strict=True))
