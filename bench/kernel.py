"""Kernel benchmarks, each against a baseline measured in the same run.

1. Kernel cost per tick with 1, 5 and 20 trivial modules, against a bare Python loop that calls the
   same modules' `step` directly. Target: at most 1 us of kernel overhead per module per tick.
2. Snapshot cost per tick (what history costs) and `backtick(1)`, each as a ratio to one physics step
   of the 200-box scene. Targets: at most 0.05 and at most 1.0.
3. Selection: step time of 200 resting boxes all simulated against 5 of them selected, and against a
   scene of only those 5 boxes (MuJoCo's own floor). Target: a speed-up of at least 20.

Run: ``.venv/bin/python bench/kernel.py``
"""

from __future__ import annotations

from timing import best_of

from dynabrain.modules.basic import Counter
from dynabrain.orchestrator.kernel.core import COLORS, BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.world import World


def kernel_overhead(ticks: int = 20000) -> None:
    print("1. kernel cost per tick (trivial modules: a counter with state)")
    print(f"   {'modules':>8} {'bare loop us':>13} {'world.tick us':>14} {'overhead/module us':>19}")
    for n in (1, 5, 20):
        world = World(step="1ms", history=1000)
        for i in range(n):
            world.add_module(Counter(f"c{i}"))
        world.tick(10)
        mods = [world.modules[f"c{i}"] for i in range(n)]

        def bare(mods=mods) -> None:
            for k in range(ticks):
                for m in mods:
                    m.step(k, 1_000_000)

        t_bare = best_of(bare) / ticks * 1e6
        t_world = best_of(lambda w=world: w.tick(ticks)) / ticks * 1e6
        per = (t_world - t_bare) / n
        print(f"   {n:>8} {t_bare:>13.3f} {t_world:>14.3f} {per:>19.3f}   target <= 1.0: "
              f"{'met' if per <= 1.0 else 'MISSED'}")
        world.close()


def box_scene(n_x: int = 20, n_y: int = 10, z: float = 0.05) -> SceneSpec:
    bodies = [BodySpec("floor", "plane", (), color=COLORS["grey"])]
    for i in range(n_x):
        for j in range(n_y):
            bodies.append(BodySpec(f"box_{i}_{j}", "box", (0.1, 0.1, 0.1), pos=(i * 0.2 - 2, j * 0.2 - 1, z),
                                   mass=0.2, color=COLORS["orange"]))
    return SceneSpec(bodies=tuple(bodies))


SELECTED = ["box_0_0", "box_5_5", "box_10_2", "box_15_7", "box_19_9"]


def physics_world(scene: SceneSpec, select: list[str] | None = None) -> World:
    from dynabrain.modules.mujoco.core import MujocoCore

    world = World("bench", step="2ms", history=200, core=MujocoCore("core", scene))
    if select is not None:
        world.make(select)
    world.tick(250)  # let the boxes settle into resting contact
    return world


def step_time(world: World, ticks: int = 500) -> float:
    """Seconds per physics step, measured on the core alone (no kernel, no history)."""
    core = world.core
    t0 = world.time_ns

    def run() -> None:
        for k in range(ticks):
            core.step(t0 + k * world.dt_ns, world.dt_ns)

    return best_of(run, 3) / ticks


def history_costs() -> None:
    print("2. history: snapshot per tick and backtick(1), against one physics step of 200 boxes")
    world = physics_world(box_scene())
    t_step = step_time(world)
    reps = 2000
    t_snap = best_of(lambda: [world._capture() for _ in range(reps)], 3) / reps
    world.tick(reps + 5)

    def back_forth() -> None:
        for _ in range(200):
            world.backtick(1)
            world.tick(1)

    t_pair = best_of(back_forth, 3) / 200
    t_tick = best_of(lambda: world.tick(200), 3) / 200
    t_back = max(t_pair - t_tick, 0.0)
    print(f"   physics step (200 boxes, all simulated): {t_step * 1e6:9.1f} us")
    print(f"   snapshot (whole-world state per tick):  {t_snap * 1e6:9.1f} us  ratio {t_snap / t_step:6.3f}"
          f"  target <= 0.05: {'met' if t_snap / t_step <= 0.05 else 'MISSED'}")
    print(f"   backtick(1):                            {t_back * 1e6:9.1f} us  ratio {t_back / t_step:6.3f}"
          f"  target <= 1.0: {'met' if t_back / t_step <= 1.0 else 'MISSED'}")
    print(f"   history: {world.history.describe()}")
    world.close()


def selection_speedup() -> None:
    print("3. selection: 200 resting boxes, all simulated vs 5 selected vs a scene of only those 5")
    everything = physics_world(box_scene())
    selected = physics_world(box_scene(), SELECTED)
    scene5 = SceneSpec(bodies=tuple(b for b in box_scene().bodies if b.name in ("floor", *SELECTED)))
    only5 = physics_world(scene5)
    t_all, t_sel, t_5 = step_time(everything), step_time(selected), step_time(only5)
    print(f"   all 200 simulated:   {t_all * 1e6:9.1f} us/step")
    print(f"   5 of 200 selected:   {t_sel * 1e6:9.1f} us/step   speed-up {t_all / t_sel:6.1f}  target >= 20: "
          f"{'met' if t_all / t_sel >= 20 else 'MISSED'}")
    print(f"   scene of only 5:     {t_5 * 1e6:9.1f} us/step   speed-up {t_all / t_5:6.1f}  (MuJoCo's floor)")
    for w in (everything, selected, only5):
        w.close()


if __name__ == "__main__":
    kernel_overhead()
    history_costs()
    selection_speedup()
