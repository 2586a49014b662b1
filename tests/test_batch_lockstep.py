"""The ``lockstep`` batch backend (issue 25): every branch in one process, advanced tick by tick together,
each module stepped once for all branches (`Module.step_batch`). Each branch is checked bit for bit
against the same branch stepped alone on a copy of the world: the humanoid with its modules, with
per-branch starts, parameters, inputs and lengths, and a branch that diverges; a module of the user's
without a batched step; one that raises for one branch; a batched step that returns the wrong shape;
branches that start from worlds of other structures; batches that go on from the last one's ends; the
swing's vector env."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import data_equivalence
from test_batch import bits, same_state
from test_gym import SWING, swing_task

from dynabrain.modules.basic import Counter
from dynabrain.orchestrator import Batch, DynabrainError, Module, Port, load_world
from dynabrain.orchestrator.brain.gym import WorldEnv, WorldVectorEnv
from dynabrain.orchestrator.kernel.module import Param

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "scenarios" / "humanoid_stand.yaml"
RECORD = ("core.pelvis.pos", "zmp.zmp", "servo.tau", "lfoot.force", "imu.acc")


@pytest.fixture(scope="module")
def humanoid():
    world = load_world(HUMANOID)
    world.tick(25)
    yield world
    world.close()


def alone(world, start: bytes, ticks: int, inputs: dict, params: dict, record=RECORD):
    """The branch stepped alone on a copy of the world, by the World API: (signals, final state), or
    the ModuleError it failed with."""
    twin = world.fork()
    try:
        twin.import_state(start)
        for name, value in params.items():
            twin.set(name, value)
        try:
            return twin.run(ticks, inputs=inputs, record=record), twin.export_state()
        except DynabrainError as err:
            return err, twin.export_state()
    finally:
        twin.close()


def check_against_alone(world, result, starts, lengths, inputs, params, record=RECORD) -> None:
    for b, ticks in enumerate(lengths):
        ref, final = alone(world, starts[b], ticks, {n: v[b][:ticks] for n, v in inputs.items()},
                           {n: v[b] for n, v in params.items()}, record)
        status = result.status[b]
        if isinstance(ref, Exception):
            assert not status.ok and status.reason == str(ref) and status.failed_tick == ref.tick, b
            assert status.ticks_done == ref.ticks_done, b
            ref = ref.recorded
        else:
            assert status.ok and status.ticks_done == ticks, (b, status)
        assert same_state(result.states[b], final), b
        for name in record:
            assert bits(result.branch(name, b)) == bits(ref[name]), (b, name)


@pytest.mark.parametrize("physics", ["mjbatch", "threads"])
def test_the_humanoid_with_its_modules_equals_each_branch_alone(humanoid, physics):
    """Two starts, per-branch friction, servo gains and lag, per-tick servo offsets, branches of
    different lengths, and one that diverges (an absurd gravity): each branch as it is alone, on
    MuJoCo's own batch (the core, the sensors and the ZMP read from its arrays) and on threads."""
    first = humanoid.export_state()
    humanoid.tick(3)
    second = humanoid.export_state()
    humanoid.backtick(3)
    lengths = [30, 30, 12, 30, 21]
    starts = [first, second, first, first, second]
    q_ref = np.zeros((5, 30, 23))
    for b in range(5):
        q_ref[b, :, :2] = 0.04 * (b - 2) * np.linspace(0, 1, 30)[:, None]
    params = {"core.friction": [0.6, 0.9, 1.2, 1.0, 0.8], "servo.kp": [40.0, 40.0, 55.0, 40.0, 40.0],
              "servo.lag": [0.0, 0.01, 0.0, 0.0, 0.004],
              "core.gravity": [[0, 0, -9.81], [0, 0, -9.81], [0, 0, -9.81], [0, 0, -1e12], [0, 0, -9.81]]}
    with Batch(humanoid, backend="lockstep", physics=physics) as batch:
        result = batch.run(lengths, starts=starts, inputs={"servo.q_ref": q_ref}, params=params, record=RECORD)
        assert result.backend == "lockstep" and result.failed == [3]
        assert not any("declined" in note for note in result.notes), result.notes
        assert "core" in result.status[3].reason
        check_against_alone(humanoid, result, starts, lengths, {"servo.q_ref": list(q_ref)},
                            {k: list(v) for k, v in params.items()})
        # a second batch on the same backend starts from the first's final states
        again = batch.run(10, starts=[result.states[0], result.states[1]], record=RECORD)
        assert again.ok
        check_against_alone(humanoid, again, [result.states[0], result.states[1]], [10, 10], {}, {})


class Kick(Module):
    """A user's module, no batched step: leans the first joint by 0.2 rad after ``at`` ticks of its own;
    ``fail_at`` > 0 raises at that tick (a module that fails for one branch)."""

    PARAMS = (Param("at", 5, runtime=True), Param("fail_at", 0, runtime=True))

    def outputs(self):
        return [Port("lean", (23,), "rad")]

    def start(self, t_ns):
        self.count = 0
        self.out["lean"][...] = 0.0

    def step(self, t_ns, dt_ns):
        self.count += 1
        if self.params["fail_at"] and self.count >= self.params["fail_at"]:
            raise RuntimeError(f"kick refused at count {self.count}")
        self.out["lean"][...] = 0.0
        self.out["lean"][0] = 0.2 if self.count >= self.params["at"] else 0.0

    def get_state(self):
        return self.count

    def set_state(self, state):
        self.count = state


class BadShape(Kick):
    """A batched step that returns one value too few per branch."""

    @classmethod
    def step_batch(cls, members, t_ns, dt_ns, inp, out, failed):
        return np.zeros((len(members), out.shape[1] - 1))


class Loose(Kick):
    """A batched step that steps each member and lets the first failure out (for which branch, it does
    not say): every branch is run again alone."""

    @classmethod
    def step_batch(cls, members, t_ns, dt_ns, inp, out, failed):
        for member in members:
            member.step(t_ns, dt_ns)


def kicked_world(cls=Kick):
    world = load_world(HUMANOID)
    world.add_module(cls("kick"), connect=[("kick.lean", "servo.q_ref")])
    world.tick(5)
    return world


@pytest.mark.parametrize("cls", [Kick, Loose])
def test_a_user_module_without_a_batched_step_and_one_that_raises_for_one_branch(cls):
    world = kicked_world(cls)
    try:
        start = world.export_state()
        params = {"kick.at": [3, 8, 12], "kick.fail_at": [0, 6, 0]}
        record = ("core.pelvis.pos", "servo.tau", "kick.lean")
        with Batch(world, backend="lockstep") as batch:
            result = batch.run(15, branches=3, params=params, record=record)
        assert result.failed == [1] and "kick refused at count 6" in result.status[1].reason
        assert any(("0, 1, 2" if cls is Loose else "branch(es) 1 ") in note for note in result.notes)
        assert "kick" in result.status[1].reason
        check_against_alone(world, result, [start] * 3, [15] * 3, {}, params, record)
    finally:
        world.close()


def test_a_batched_step_of_the_wrong_shape_is_an_error_naming_module_and_port():
    world = kicked_world(BadShape)
    try:
        with Batch(world, backend="lockstep") as batch:
            with pytest.raises(DynabrainError, match=r"module 'kick' \(BadShape\).*lean \(23,\).*shape \(2, 23\)"):
                batch.run(5, branches=2)
            assert world.tick_count == 5
    finally:
        world.close()


def test_branches_from_worlds_of_other_structures_are_stepped_in_groups_of_their_own(humanoid):
    """A module added in one start's world (a dynabrain module: the branch's world makes it on import)."""
    plain = humanoid.export_state()
    twin = humanoid.fork()
    try:
        twin.add_module(Counter("count"))
        twin.tick(2)
        counted = twin.export_state()
    finally:
        twin.close()
    starts = [plain, counted, plain]
    record = ("core.pelvis.pos", "servo.tau")
    with Batch(humanoid, backend="lockstep") as batch:
        result = batch.run(8, starts=starts, record=record)
    assert result.ok and any("2 lockstep groups" in note for note in result.notes)
    check_against_alone(humanoid, result, starts, [8] * 3, {}, {}, record)


def test_batches_that_go_on_from_the_last_ones_ends_equal_one_long_run(humanoid):
    """A vector env's steps: each batch starts from the states the last one returned (in another order
    the second time): the branches go on where they ended, and equal each branch run alone as long."""
    start = humanoid.export_state()
    q_ref = np.zeros((2, 15, 23))
    q_ref[0, :, 0], q_ref[1, :, 1] = 0.05, -0.05
    record = ("core.pelvis.pos", "servo.tau")
    with Batch(humanoid, backend="lockstep") as batch:
        states, order = [start, start], [0, 1]
        pieces = {name: [[], []] for name in record}
        for k, flip in enumerate((False, True, False)):
            if flip:
                order, states = order[::-1], states[::-1]
            result = batch.run(5, starts=states, inputs={"servo.q_ref": q_ref[order, 5 * k:5 * k + 5]}, record=record)
            assert result.ok
            states = result.states
            for b, branch in enumerate(order):
                for name in record:
                    pieces[name][branch].append(result.signals[name][b])
    for branch in (0, 1):
        ref, final = alone(humanoid, start, 15, {"servo.q_ref": q_ref[branch]}, {}, record)
        assert same_state(states[order.index(branch)], final), branch
        for name in record:
            assert bits(np.concatenate(pieces[name][branch])) == bits(ref[name]), (branch, name)


def test_the_swing_vector_env_on_lockstep_equals_single_envs():
    """Each copy's steps (batches going on from the last one's ends, resets importing a new start with
    the reset hook's servo gain) are the single env's, bit for bit, autoresets included."""
    import gymnasium

    world = load_world(SWING)
    world.remove_module("pump")
    task = swing_task(on_reset=lambda world, rng: world.set("servo.kp", float(rng.uniform(15, 25))))
    envs = WorldVectorEnv(world, 2, backend="lockstep", **task)
    ref = gymnasium.vector.SyncVectorEnv([lambda: WorldEnv(world.fork(world.name), **task) for _ in range(2)])
    try:
        envs.action_space.seed(5)
        assert data_equivalence(envs.reset(seed=7), ref.reset(seed=7), exact=True)
        for k in range(17):
            actions = envs.action_space.sample()
            assert data_equivalence(envs.step(actions), ref.step(actions), exact=True), k
    finally:
        envs.close()
        ref.close()
        world.close()


def test_an_animated_robot_and_a_world_made_in_code():
    """The tendon arm animated (its core steps alone, its motion set between the halves of the step) in
    a world made in code (no scenario to rebuild it from), each branch its own joint targets."""
    from test_robot_models import arm_world

    world = arm_world()
    try:
        world.make(["box"])
        world.tick(3)
        start = world.export_state()
        q0 = np.array([world.get("core.shoulder.q"), world.get("core.elbow.q")])
        targets = np.stack([q0 + np.outer(np.linspace(0, 1, 20), [0.2 * b, -0.1 * b]) for b in range(3)])
        record = ("core.shoulder.q", "core.elbow.qd", "box.pos")
        with Batch(world, backend="lockstep") as batch:
            result = batch.run(20, branches=3, inputs={"core.joint_target": targets}, record=record)
        assert result.ok
        check_against_alone(world, result, [start] * 3, [20] * 3, {"core.joint_target": list(targets)}, {}, record)
    finally:
        world.close()


def test_mujocos_own_batch_declines_what_it_cannot_step_bit_for_bit(humanoid):
    """A sensor with noise in one branch reads the core's data in its own step: MuJoCo's batch declines
    the group (said in the notes) and the branches are stepped on threads, each as it is alone. A
    branch whose velocity input holds a value at a tick leaves the lockstep and is run alone."""
    start = humanoid.export_state()
    params = {"imu.noise": [0.0, 0.05, 0.0]}
    with Batch(humanoid, backend="lockstep", physics="mjbatch") as batch:
        result = batch.run(12, branches=3, params=params, record=RECORD)
        assert result.ok and any("physics 'mjbatch' declined" in n and "imu" in n for n in result.notes), result.notes
    check_against_alone(humanoid, result, [start] * 3, [12] * 3, {}, {k: list(v) for k, v in params.items()})

    vel = np.full((2, 12, 1, 6), np.nan)  # the pelvis (the free body): a twist from tick 4 in branch 1
    vel[1, 4:] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.1]
    with Batch(humanoid, backend="lockstep", physics="mjbatch") as batch:
        result = batch.run(12, branches=2, inputs={"core.body_velocity": vel}, record=RECORD)
        assert result.ok and any("failed in lockstep" in n for n in result.notes), result.notes
    check_against_alone(humanoid, result, [start] * 2, [12] * 2, {"core.body_velocity": list(vel)}, {})


def test_fmu_instances_of_the_branches_step_in_one_call_each_as_it_is_alone(monkeypatch):
    """The servo FMU (built from fmus/servo) of N branches stepped by one call into the C helper a tick
    (`fused.step_each`), each branch its own gains and targets, one given a non-finite target (its FMU
    step fails, it alone): every branch as it is alone, bit for bit."""
    from dynabrain.orchestrator.fmu import fused, module

    calls = []
    real = fused.step_each
    monkeypatch.setattr(module, "step_each", lambda members, t_ns, failed: calls.append(len(members))
                        or real(members, t_ns, failed))
    world = load_world(ROOT / "scenarios" / "fmu_servo.yaml")
    try:
        world.tick(10)
        start = world.export_state()
        q_ref = np.zeros((4, 40, 2))
        for b in range(4):
            q_ref[b] = [0.1 * b, -0.2 * b]
        q_ref[2, 25:] = np.nan
        params = {"servo.kp": [20.0, 35.0, 20.0, 10.0]}
        record = ("core.j1.q", "servo.tau", "core.j2.qd")
        with Batch(world, backend="lockstep") as batch:
            result = batch.run(40, branches=4, inputs={"servo.q_ref": q_ref}, params=params, record=record)
        assert result.failed == [2] and calls and max(calls) == 4
        check_against_alone(world, result, [start] * 4, [40] * 4, {"servo.q_ref": list(q_ref)},
                            {k: list(v) for k, v in params.items()}, record)
    finally:
        world.close()


class Peek(Module):
    """A user's module that reads the core's MuJoCo data itself (the pelvis height)."""

    def outputs(self):
        return [Port("z", (), "m")]

    def setup(self, ctx):
        self._core = ctx.core  # (a fork's copy holds the fork's core)

    def start(self, t_ns):
        self.out["z"][...] = self._core.mj.data.qpos[2]

    def step(self, t_ns, dt_ns):
        self.out["z"][...] = self._core.mj.data.qpos[2]


def test_a_module_reading_the_cores_data_itself_makes_mujocos_batch_decline():
    """MuJoCo's batch keeps no branch's MjData current while it steps: a module holding the core is seen,
    the group is stepped on threads (said), each branch as it is alone."""
    world = load_world(HUMANOID)
    try:
        world.add_module(Peek("peek"))
        world.tick(5)
        start = world.export_state()
        with Batch(world, backend="lockstep", physics="mjbatch") as batch:
            result = batch.run(10, branches=2, params={"core.friction": [0.7, 1.1]}, record=("peek.z", *RECORD))
        assert result.ok and any("declined" in n and "peek" in n for n in result.notes), result.notes
        check_against_alone(world, result, [start] * 2, [10] * 2, {}, {"core.friction": [0.7, 1.1]},
                            ("peek.z", *RECORD))
    finally:
        world.close()
