"""Planning and learning benchmark: what a brain thinking with its simulator gets done per second, each
figure measured in this run (one function per section; `main` runs them in turn).

Swing episodes (`scenarios/swing_learning.yaml`: the humanoid on the swing, 5 modules besides the
core; an episode is ``--horizon`` seconds from t = 0):

1. one world, serial: ``import_state`` of the start, then ``run`` the episode, the policy a module
   (SwingPolicy) in the world: episodes per second, the baseline;
2. a Batch of ``--episodes`` episodes on ``processes``, each branch with its own policy weights (as one
   CMA-ES generation is run): episodes per second and the ratio to 1;
3. Gymnasium, the policy outside the world (the same formula in numpy, without its speed limit,
   acting on the four leg ports once every ``--ticks-per-step`` ticks): one `WorldEnv`, then a
   `WorldVectorEnv` of ``--copies`` copies on ``serial`` and on ``processes``: episodes per second
   and the ratios to the single env.

The block-moving task (`examples/blocks_planner.py`, `scenarios/blocks.yaml`): the planning time, the
nodes expanded and the children simulated per second, with the children of a node evaluated on
``serial`` and as one batch on ``processes``; the careful planner (one block at a time) and the one
that may push fast.

The machine's load (1-minute average) is printed before and after: on a busy machine the ratios hold
better than the absolute figures.

Run: ``.venv/bin/python bench/plan.py [--horizon 4] [--episodes 16] [--copies 8] [--ticks-per-step 10]``
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from timing import best_of

from dynabrain.orchestrator import Batch, load_world
from dynabrain.orchestrator.brain.gym import WorldEnv, WorldVectorEnv

ROOT = Path(__file__).resolve().parents[1]
SWING = ROOT / "scenarios" / "swing_learning.yaml"
ANGLE, RATE = "core.swing_pivot.q", "core.swing_pivot.qd"
LEGS = {"servo.l_hip_pitch.q_ref": "hip", "servo.r_hip_pitch.q_ref": "hip", "servo.l_knee.q_ref": "knee",
        "servo.r_knee.q_ref": "knee"}


def load() -> str:
    return f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


# -- swing episodes ---------------------------------------------------------------------------------------
def swing_serial(world, ticks: int) -> float:
    """Episodes per second of one world: restore the start state, run the episode."""
    start = world.export_state()

    def episode() -> None:
        world.import_state(start)
        world.run(ticks, record=["swings.amplitude"])

    return 1.0 / best_of(episode, repeats=5)


def swing_batch(world, ticks: int, episodes: int) -> tuple[float, float]:
    """(episodes per second of a Batch on processes, seconds for its workers to start)."""
    weights = np.random.default_rng(0).normal(size=(episodes, 3)) * [10.0, 10.0, 1.0]
    params = {f"policy.{name}": weights[:, k].tolist() for k, name in enumerate(("w_angle", "w_rate", "bias"))}
    t0 = time.perf_counter()
    with Batch(world, backend="processes") as batch:
        assert batch.run(2, branches=1).ok  # start the workers
        startup = time.perf_counter() - t0
        best = float("inf")
        for _ in range(3):
            result = batch.run(ticks, branches=episodes, params=params, record=["swings.amplitude"], keep_states=False)
            assert result.ok, [str(s) for s in result.status if not s.ok]
            best = min(best, result.wall_s)
    return episodes / best, startup


POLICY = ("w_angle", "w_rate", "bias", "hip_amplitude", "knee_amplitude")


def policy_actions(policy: dict[str, float], obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """SwingPolicy's offsets from an observation (one copy's or a vector env's batch), for the leg ports."""
    drive = np.tanh(policy["w_angle"] * obs[ANGLE] + policy["w_rate"] * obs[RATE] + policy["bias"])
    return {port: policy[f"{joint}_amplitude"] * drive for port, joint in LEGS.items()}


def swing_task(world, ticks: int, ticks_per_step: int) -> tuple[dict[str, float], dict]:
    """The scenario's policy weights, and the env's task once the policy module has left the world."""
    policy = {name: float(world.get(f"policy.{name}")) for name in POLICY}
    world.remove_module("policy")  # the agent drives the legs
    return policy, dict(observe=[ANGLE, RATE], act=dict.fromkeys(LEGS, (-2.0, 2.0)), ticks_per_step=ticks_per_step,
                        max_steps=ticks // ticks_per_step, reward=lambda obs, action: abs(float(obs[ANGLE])))


def swing_env(ticks: int, ticks_per_step: int) -> float:
    """Episodes per second of one WorldEnv, the policy stepped outside the world."""
    with load_world(SWING) as world:
        policy, task = swing_task(world, ticks, ticks_per_step)
        env = WorldEnv(world, **task)

        def episode() -> None:
            obs, _ = env.reset(seed=0)
            done = False
            while not done:
                obs, _, terminated, truncated, _ = env.step(policy_actions(policy, obs))
                done = terminated or truncated

        return 1.0 / best_of(episode, repeats=3)


def swing_vector_env(ticks: int, ticks_per_step: int, copies: int, backend: str) -> tuple[float, float]:
    """(episodes per second of a WorldVectorEnv, seconds to make it and start its workers)."""
    with load_world(SWING) as world:
        t0 = time.perf_counter()
        policy, task = swing_task(world, ticks, ticks_per_step)
        envs = WorldVectorEnv(world, copies, backend=backend, **task)
        envs.step(policy_actions(policy, envs.reset(seed=0)[0]))  # start the workers
        startup = time.perf_counter() - t0

        def episodes() -> None:
            obs, _ = envs.reset(seed=0)
            done = np.zeros(copies, dtype=bool)
            while not done.all():
                obs, _, terminated, truncated, _ = envs.step(policy_actions(policy, obs))
                done |= terminated | truncated

        rate = copies / best_of(episodes, repeats=3)
        envs.close()
    return rate, startup


def swing_episodes(opts: argparse.Namespace) -> None:
    world = load_world(SWING)
    ticks = round(opts.horizon / (world.dt_ns * 1e-9))
    steps = ticks // opts.ticks_per_step
    print(f"swing episodes: {opts.horizon:g} s each ({ticks} ticks), the humanoid on the swing "
          f"({len(world.modules)} modules); {load()}")
    base = swing_serial(world, ticks)
    print(f"   one world, import_state + run:          {base:8.1f} episodes/s   1.00x")
    rate, startup = swing_batch(world, ticks, opts.episodes)
    print(f"   Batch of {opts.episodes} on processes:           {rate:8.1f} episodes/s   {rate / base:4.2f}x   "
          f"(workers up in {startup:.2f} s)")
    world.close()
    print(f"   the policy outside the world, {steps} steps of {opts.ticks_per_step} ticks an episode:")
    single = swing_env(ticks, opts.ticks_per_step)
    print(f"   WorldEnv (one copy):                    {single:8.1f} episodes/s   1.00x   "
          f"({single * steps:.0f} steps/s; {single / base:.2f}x the world alone)")
    rates = {}
    for backend in ("serial", "processes", "lockstep"):
        rate, startup = rates[backend] = swing_vector_env(ticks, opts.ticks_per_step, opts.copies, backend)
        print(f"   WorldVectorEnv, {opts.copies} copies on {backend:<10} {rate:8.1f} episodes/s   "
              f"{rate / single:4.2f}x   (made in {startup:.2f} s)")
    ratio = rates["lockstep"][0] / rates["processes"][0]
    print(f"   target vector env on lockstep >= 3x processes (issue 25): {'met' if ratio >= 3 else 'MISSED'} "
          f"({ratio:.2f}x)")
    print(f"   {load()}")


def blocks(opts: argparse.Namespace) -> None:
    import sys

    sys.path.insert(0, str(ROOT / "examples"))
    import blocks_planner as bp

    world = load_world(bp.SCENARIO)
    world.tick(50)
    print(f"block-moving task: {len(bp.actions(world.dt_ns * 1e-9, ('slow', 'fast')))} pushes to try per node, "
          f"{bp.TICKS} ticks each; {load()}")
    batches = {backend: Batch(world, backend=backend) for backend in ("serial", "processes")}
    batches["processes"].run(2, branches=2)  # the workers start before the clock does
    for name, speeds, careful in (("careful", ("slow",), True), ("with the simulator", ("slow", "fast"), False)):
        for backend, batch in batches.items():
            p = bp.plan(world, speeds, careful=careful, batch=batch)
            print(f"   {name:<19} {backend:<10} {'found' if p.found else 'NO PLAN'}: {len(p.actions)} pushes, "
                  f"{p.stats.wall_s:6.2f} s, {p.stats.expanded:3d} nodes expanded, "
                  f"{p.stats.nodes_per_s:6.1f} children/s ({p.stats.ticks / p.stats.wall_s:8.0f} ticks/s)")
    for batch in batches.values():
        batch.close()
    world.close()
    print(f"   {load()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--horizon", type=float, default=4.0, help="seconds per swing episode")
    ap.add_argument("--episodes", type=int, default=16, help="episodes per Batch run")
    ap.add_argument("--copies", type=int, default=8, help="copies in the vector env")
    ap.add_argument("--ticks-per-step", type=int, default=10)
    ap.add_argument("--only", choices=("swing", "blocks"), help="run one part")
    opts = ap.parse_args()
    if opts.only != "blocks":
        swing_episodes(opts)
    if opts.only != "swing":
        blocks(opts)


if __name__ == "__main__":
    main()
