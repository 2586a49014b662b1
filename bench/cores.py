"""The two physics cores on the same scenes: step cost at the step sizes each needs for the same
accuracy, measured in one run (MuJoCo's figures are the baseline of the ratios).

1. Two cubes on a floor. Cost of a step with both resting (the issue's figure for scale: MuJoCo
   about 6 us per 2 ms step; Exudyn's penalty contact 1e-5 s steps at about 12 us each), and what
   each Exudyn step size keeps of the accuracy of a flat drop from 30 cm: how far the cubes slip
   sideways (exact: 0), how deep they sink (exact: 0) and how much they tilt (exact: 0).
2. The pendulum chain (scenarios/pendulum_chain.yaml): link positions over its first 2 s against a
   reference (Exudyn at a 25 us step; MuJoCo converges to it), and the cost of each core at the
   steps that keep them within about 1 mm.
3. The robot arm (scenarios/robot_arm.yaml) and the rope swing (scenarios/rope_swing_exudyn.yaml,
   Exudyn only): cost per 2 ms tick at the defaults.

Run: ``.venv/bin/python bench/cores.py``
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from timing import best_of

from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator.kernel.core import BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
TICK = 0.002


def tick_cost(world: World, ticks: int = 300) -> float:
    """Seconds per module step of the core alone (no kernel, no history)."""
    core, t0 = world.core, world.time_ns

    def run() -> None:
        for k in range(ticks):
            core.step(t0 + k * world.dt_ns, world.dt_ns)

    return best_of(run, 3) / ticks


def cubes(z_a: float, z_b: float) -> SceneSpec:
    return SceneSpec(bodies=(BodySpec("floor", "plane", ()),
                             BodySpec("a", "box", (0.1, 0.1, 0.1), pos=(0.0, 0.0, z_a), mass=0.05),
                             BodySpec("b", "box", (0.2, 0.2, 0.15), pos=(0.4, 0.1, z_b), mass=0.06)))


def cube_world(cls, scene: SceneSpec, **params) -> World:
    return World(cls.ENGINE, step="2ms", core=cls("core", scene, friction=0.8, restitution=0.2, **params))


def drop_accuracy(cls, **params) -> tuple[float, float, float]:
    """(slip mm, sink mm, tilt deg) of the worse cube, 1.5 s after a flat drop from 30 cm."""
    world = cube_world(cls, cubes(0.35, 0.375), **params)
    world.tick(750)
    slip = sink = tilt = 0.0
    for name, start, half in (("a", (0.0, 0.0), 0.05), ("b", (0.4, 0.1), 0.075)):
        pos, quat = world.get(f"{name}.pos"), world.get(f"{name}.quat")
        slip = max(slip, 1000 * float(np.linalg.norm(pos[:2] - start)))
        sink = max(sink, 1000 * (half - float(pos[2])))
        tilt = max(tilt, float(np.degrees(2 * np.arccos(min(1.0, abs(float(quat[0])))))))
    world.close()
    return slip, sink, tilt


EXUDYN_ROWS = (
    ("1e-5 s, stiff (as the issue)", {"substeps": 200, "contact_frequency": 1000.0, "friction_zone": 1e-3}),
    ("0.1 ms, wn 0.5/step", {"substeps": 20}),
    ("0.25 ms, wn 0.5/step", {"substeps": 8}),
    ("0.5 ms, default", {"substeps": 4}),
    ("0.5 ms, zone 5 cm/s", {"substeps": 4, "friction_zone": 0.05}),
    ("1 ms", {"substeps": 2}),
    ("2 ms", {"substeps": 1}),
)


def two_cubes() -> None:
    print("1. two cubes on a floor: cost of a 2 ms tick at rest, accuracy of a flat drop from 30 cm")
    print(f"   {'core, settings':34} {'us/step':>8} {'us/tick':>8} {'x MuJoCo':>8} {'slip mm':>8} {'sink mm':>8}"
          f" {'tilt deg':>8}")
    base = None
    rows = [(MujocoCore, "2 ms", {"substeps": 1}), (MujocoCore, "0.5 ms", {"substeps": 4})]
    rows += [(ExudynCore, label, params) for label, params in EXUDYN_ROWS]
    for cls, label, params in rows:
        world = cube_world(cls, cubes(0.05, 0.075), **params)
        world.tick(100)
        cost = tick_cost(world, 100 if params["substeps"] > 50 else 500)
        world.close()
        try:
            slip, sink, tilt = drop_accuracy(cls, **params)
            accuracy = f"{slip:8.2f} {sink:8.3f} {tilt:8.2f}"
        except Exception as exc:  # a step too large for the contacts: it diverges
            accuracy = f"   diverged: {type(exc).__name__}"
        base = base or cost
        name = f"{cls.ENGINE} {label}"
        print(f"   {name:34} {cost / params['substeps'] * 1e6:8.1f} {cost * 1e6:8.1f} {cost / base:8.1f} {accuracy}")
    print("   Exudyn defaults: 0.5 ms steps, contacts at wn = 0.5/step = 1000 rad/s, friction regularised below "
          "max(1 cm/s, 4 mu g step)")


def chain(core: str, substeps: int, **params) -> tuple[np.ndarray, float]:
    scenario = load_scenario(SCENARIOS / "pendulum_chain.yaml")
    scenario.model.core.update(params)
    world = scenario.build(core=core)
    world.set("core.substeps", substeps)
    out = []
    for _ in range(1000):
        world.tick()
        out.append(np.concatenate([world.get(f"l{i}.pos") for i in range(1, 5)]))
    cost = tick_cost(world, 200)
    world.close()
    return np.array(out), cost


def chain_accuracy() -> None:
    print("2. pendulum chain (4 links released from horizontal): max link position error over 2 s, cost")
    reference, _ = chain("exudyn", 80)
    print(f"   {'core':28} {'step':>8} {'error mm':>9} {'us/tick':>8} {'x MuJoCo 2ms':>12}")
    base = None
    rows = [("mujoco", 1, {}), ("mujoco", 4, {}), ("mujoco", 16, {}), ("exudyn", 1, {}), ("exudyn", 4, {}),
            ("exudyn", 1, {"link_contacts": False}), ("exudyn", 4, {"link_contacts": False})]
    for core, substeps, params in rows:
        traj, cost = chain(core, substeps, **params)
        base = base or cost
        error = 1000 * np.abs(traj - reference).max()
        name = core + (" (links touch nothing)" if params else "")
        print(f"   {name:28} {TICK / substeps * 1e3:6.3f}ms {error:9.3f} {cost * 1e6:8.1f} {cost / base:12.1f}")
    print("   at one step size Exudyn's error is about a third of MuJoCo's; both shrink about linearly with the step "
          "(joint damping is a velocity-dependent force, which velocity Verlet integrates at first order). Most of "
          "Exudyn's cost is the contact spheres on the links (each one a forward kinematics in Exudyn)")


def scenario_cost() -> None:
    print("3. cost per 2 ms tick at the defaults")
    print(f"   {'scenario':18} {'mujoco us':>10} {'exudyn us':>10} {'ratio':>6} {'exudyn step':>12}")
    for name in ("two_cubes_exudyn", "pendulum_chain", "robot_arm", "rope_swing_exudyn"):
        costs = {}
        for core in ("mujoco", "exudyn"):
            try:
                world = load_scenario(SCENARIOS / f"{name}.yaml").build(core=core)
            except Exception:  # MuJoCo refuses the flexible bodies
                costs[core] = float("nan")
                continue
            world.tick(100)
            costs[core] = tick_cost(world, 200)
            step = world.core.engine_step if core == "exudyn" else TICK
            world.close()
        mj, ex = costs["mujoco"], costs["exudyn"]
        mj_text = f"{mj * 1e6:10.1f}" if mj == mj else f"{'refused':>10}"
        ratio = f"{ex / mj:6.1f}" if mj == mj else f"{'-':>6}"
        print(f"   {name:18} {mj_text} {ex * 1e6:10.1f} {ratio} {step * 1e6:9.0f} us")


if __name__ == "__main__":
    two_cubes()
    chain_accuracy()
    scenario_cost()
