"""Gymnasium environments over a World (orchestrator/brain/gym.py): Gymnasium's own checker passes, a
reset restores the snapshot and seeds the hook, bad specs and out-of-space actions are refused with
names, a diverging branch ends its episode, and the vector env's copies (serial and processes) equal
Gymnasium's SyncVectorEnv of single envs bit for bit, autoresets included."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env, data_equivalence
from gymnasium.vector import AutoresetMode

from dynabrain.orchestrator import Module, Param, Port, World, load_world
from dynabrain.orchestrator.brain.gym import SpaceError, WorldEnv, WorldVectorEnv, clip_actions

SWING = Path(__file__).resolve().parent.parent / "scenarios" / "swing.yaml"
ANGLE, RATE = "core.swing_pivot.q", "core.swing_pivot.qd"
HIP, KNEE = "servo.l_hip_pitch.q_ref", "servo.l_knee.q_ref"


def swing_task(**changes):
    """The swing with the agent's legs (the pump removed): observe the hinge, drive one hip and knee."""
    task = dict(observe={ANGLE: (-4, 4), RATE: (-20, 20)}, act={HIP: (-1.2, 1.2), KNEE: (-1.5, 0.0)},
                reward=lambda obs, action: abs(float(obs[ANGLE])), ticks_per_step=10, max_steps=7)
    task.update(changes)
    return task


@pytest.fixture(scope="module")
def swing():
    world = load_world(SWING)
    world.remove_module("pump")
    yield world
    world.close()


def test_check_env_passes_and_reset_restores_the_snapshot(swing):
    env = WorldEnv(swing, **swing_task())
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*render modes.*")  # no gymnasium.make spec: nothing to render
        check_env(env)
    assert env.action_space[HIP].shape == () and env.observation_space[ANGLE].dtype == np.float64
    first, _ = env.reset(seed=3)
    actions = [{HIP: 0.8 * (-1) ** k, KNEE: -0.3} for k in range(7)]
    run1 = [env.step(a) for a in actions]
    assert run1[-1][3] and not run1[-1][2]  # truncated after max_steps
    with pytest.raises(Exception, match="call reset"):
        env.step(actions[0])
    again, _ = env.reset(seed=3)
    assert data_equivalence(first, again, exact=True)
    assert data_equivalence(run1, [env.step(a) for a in actions], exact=True)
    assert swing.tick_count == 70


def test_on_reset_gets_the_seeded_generator_and_terminated_ends_the_episode(swing):
    drawn = []

    def on_reset(world, rng):
        drawn.append(rng.uniform(0.5, 1.5))
        world.set("servo.kp", 20.0 * drawn[-1])

    env = WorldEnv(swing, **swing_task(on_reset=on_reset, terminated=lambda obs, action: abs(obs[ANGLE]) > 1e-4,
                                       max_steps=None))
    env.reset(seed=11)
    env.reset(seed=11)
    env.reset(seed=12)
    assert drawn[0] == drawn[1] != drawn[2]
    assert swing.get("servo.kp") == 20.0 * drawn[2]
    steps = 0
    while True:
        _, _, terminated, truncated, _ = env.step({HIP: 1.0, KNEE: -1.0})
        steps += 1
        if terminated:
            break
    assert not truncated and steps < 20


def test_actions_out_of_the_space_are_refused_and_clipping_is_explicit(swing):
    env = WorldEnv(swing, **swing_task())
    env.reset(seed=0)
    tick = swing.tick_count
    refused = r"l_hip_pitch\.q_ref = 2\. is outside the action space \[-1\.2, 1\.2\].*clip_actions"
    with pytest.raises(SpaceError, match=refused):
        env.step({HIP: 2.0, KNEE: 0.0})
    with pytest.raises(SpaceError, match="outside"):
        env.step({HIP: math.nan, KNEE: 0.0})
    with pytest.raises(SpaceError, match=r"lacks a value for port 'servo\.l_knee\.q_ref'"):
        env.step({HIP: 0.0})
    with pytest.raises(SpaceError, match=r"has no port 'servo\.l_hip_pitch\.q_rf'.*did you mean"):
        env.step({"servo.l_hip_pitch.q_rf": 0.0, KNEE: 0.0})
    with pytest.raises(SpaceError, match=r"shape \(2,\); the port's shape is \(\)"):
        env.step({HIP: [0.0, 0.0], KNEE: 0.0})
    assert swing.tick_count == tick  # nothing ran

    clipped = clip_actions(WorldEnv(swing, **swing_task()))
    assert np.isinf(clipped.action_space[HIP].high)
    clipped.reset(seed=0)
    clipped.step({HIP: 5.0, KNEE: 1.0})
    assert swing.get(HIP) == 1.2 and swing.get(KNEE) == 0.0


@pytest.mark.parametrize(("spec", "message"), [
    (dict(observe=["core.swing_pivot.qq"]), "no signal 'core.swing_pivot.qq'.*did you mean"),
    (dict(observe=["servo.kp"]), "no signal 'servo.kp'"),
    (dict(observe={ANGLE: (1, -1)}), "low <= high"),
    (dict(act={HIP: (-1, 1, 2)}), "a pair"),
    (dict(act={HIP: None}), "needs its bounds"),
    (dict(act={HIP: ([-1, 0], [1, 1])}), "not numbers of the port's shape"),
    (dict(act={"servo.l_hip_pitch.q_rf": (-1, 1)}), "act:.*did you mean"),
    (dict(act={"servo.kp": (0, 10)}), "is a parameter"),
    (dict(act={"servo.ctrl": (-1, 1)}), "is an output"),
    (dict(act={"servo.q": (-1, 1)}), "driven by enc.q"),
    (dict(ticks_per_step=0), "ticks_per_step"),
    (dict(max_steps=0), "max_steps"),
    (dict(reward=None), "reward"),
])
def test_bad_specs_are_refused_at_construction(swing, spec, message):
    with pytest.raises(SpaceError, match=message):
        WorldEnv(swing, **swing_task(**spec))


class Fuse(Module):
    """Passes ``x`` to ``y``; a step with ``x`` above ``limit`` raises (a stand-in for a diverging physics)."""

    PARAMS = (Param("limit", 1.0, runtime=True),)

    def inputs(self):
        return [Port("x", ())]

    def outputs(self):
        return [Port("y", ())]

    def step(self, t_ns, dt_ns):
        if float(self.inp["x"]) > self.params["limit"]:
            raise FloatingPointError("diverged")
        self.out["y"][...] = self.inp["x"]


def fuse_world() -> World:
    world = World("fuse", step="1ms")
    world.add_module(Fuse("fuse"))
    return world


def test_a_failing_branch_ends_the_episode_with_its_error():
    world = fuse_world()
    env = WorldEnv(world, observe=["fuse.y"], act={"fuse.x": (0, 2)}, reward=lambda o, a: float(o["fuse.y"]),
                   ticks_per_step=5, failure_reward=-10.0)
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step({"fuse.x": 0.5})
    assert (float(obs["fuse.y"]), reward, terminated, info) == (0.5, 0.5, False, {})
    obs, reward, terminated, truncated, info = env.step({"fuse.x": 1.5})
    assert terminated and not truncated and reward == -10.0
    assert "diverged" in info["error"] and info["failed_tick"] == 5 and world.tick_count == 5
    assert float(obs["fuse.y"]) == 0.5  # the state the world rolled back to
    with pytest.raises(Exception, match="call reset"):
        env.step({"fuse.x": 0.5})
    env.reset()
    assert world.tick_count == 0
    world.close()


def test_vector_env_matches_gymnasiums_sync_vector_env_and_fails_per_copy():
    world = fuse_world()
    task = dict(observe=["fuse.y"], act={"fuse.x": (0, 2)}, reward=lambda o, a: float(o["fuse.y"]), ticks_per_step=3,
                max_steps=4)
    envs = WorldVectorEnv(world, 3, **task)
    ref = gymnasium.vector.SyncVectorEnv([lambda: WorldEnv(world.fork("fuse"), **task) for _ in range(3)])
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert data_equivalence(envs.reset(seed=1), ref.reset(seed=1), exact=True)
    for k in range(7):
        actions = {"fuse.x": np.array([0.2 * k, 1.5 if k == 2 else 0.1, 0.3])}
        got, want = envs.step(actions), ref.step(actions)
        assert data_equivalence(got, want, exact=True), (k, got, want)
        if k == 2:  # copy 1 failed: terminated, with its error in the vector info
            assert list(got[2]) == [False, True, False] and got[4]["_error"].tolist() == [False, True, False]
        if k == 3:  # ... and is reset on the next step, its action ignored
            assert got[1][1] == 0.0 and not got[2][1]
    with pytest.raises(SpaceError, match=r"copy 2.*outside"):
        envs.step({"fuse.x": np.array([0.0, 0.0, 3.0])})
    with pytest.raises(SpaceError, match=r"need \(3,\)"):
        envs.step({"fuse.x": np.zeros(2)})
    envs.close()
    ref.close()
    world.close()


@pytest.mark.parametrize("backend", ["serial", "processes"])
def test_vector_env_copies_equal_the_single_env_on_the_swing(swing, backend):
    """Each copy runs through the Batch from its own state; a copy's trajectory is the single env's for
    the same actions, bit for bit, across episodes (max_steps 7, so resets at steps 8 and 16)."""
    task = swing_task(on_reset=lambda world, rng: world.set("servo.kp", float(rng.uniform(15, 25))))
    envs = WorldVectorEnv(swing, 2, backend=backend, workers=2 if backend == "processes" else None, **task)
    ref = gymnasium.vector.SyncVectorEnv([lambda: WorldEnv(swing.fork(swing.name), **task) for _ in range(2)])
    envs.action_space.seed(5)
    assert data_equivalence(envs.reset(seed=7), ref.reset(seed=7), exact=True)
    for k in range(17):
        actions = envs.action_space.sample()
        got, want = envs.step(actions), ref.step(actions)
        assert data_equivalence(got, want, exact=True), k
    assert got[1].min() > 0  # the swing moves
    envs.close()
    ref.close()


def test_vector_env_hands_the_reward_function_what_the_single_env_does():
    seen = []

    def reward(obs, action):
        seen.append((type(obs["fuse.y"]), np.shape(obs["fuse.y"]), type(action["fuse.x"]), np.shape(action["fuse.x"])))
        return 0.0

    world = fuse_world()
    task = dict(observe=["fuse.y"], act={"fuse.x": (0, 2)}, reward=reward)
    single = WorldEnv(world.fork("fuse"), **task)
    single.reset(seed=0)
    single.step({"fuse.x": 0.5})
    envs = WorldVectorEnv(world, 2, **task)
    envs.reset(seed=0)
    envs.step({"fuse.x": np.array([0.5, 0.5])})
    assert seen == [(np.ndarray, (), np.ndarray, ())] * 3
    envs.close()
    single.world.close()
    world.close()
