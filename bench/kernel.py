"""Kernel benchmarks, each against a baseline measured in the same run.

1. Kernel cost per tick with 1, 5 and 20 trivial modules, against a bare Python loop that calls the
   same modules' `step` directly (the two interleaved, best of 9, history full at depth 1000). Targets:
   kernel overhead per module per tick at most 0.5 us with one module, at most 0.1 us with 20. What
   the overhead holds with one module is printed too (the generated tick with its finite-output check,
   the history entry, and the rest: the loop, the events check, the observers check).
2. Snapshot cost per tick (what history costs) and `backtick(1)`, each as a ratio to one physics step
   of the 200-box scene. Targets: at most 0.05 and at most 1.0. The snapshot figure is what a state
   every tick costs a world whose history is full (each tick makes a state and drops the oldest; the
   same world with an entry that does nothing, interleaved). Also printed: making states alone, a few
   hundred held at once (about 70 KiB each: fresh memory, so mostly the allocator and page faults,
   which a full history's recycled memory does not pay).
3. Selection: step time of 200 resting boxes all simulated against 5 of them selected, the others frozen
   (static obstacles, `make(objects)`) or absent (out of the simulation, `make(objects, others="absent")`,
   the floor selected with them), and against a scene of only those 5 boxes (MuJoCo's own floor). Target:
   a speed-up of at least 35 with the others absent.

Run: ``.venv/bin/python bench/kernel.py``
"""

from __future__ import annotations

from timing import best_of, best_of_each

from dynabrain.modules.basic import Counter
from dynabrain.orchestrator.kernel.core import COLORS, BodySpec, SceneSpec
from dynabrain.orchestrator.kernel.world import KEYFRAME_EVERY, World

TARGETS = {1: 0.5, 20: 0.1}
"""Kernel overhead per module per tick at most (us), by number of modules."""


def kernel_overhead(ticks: int = 20000) -> None:
    print("1. kernel cost per tick (trivial modules: a counter with state)")
    print(f"   {'modules':>8} {'bare loop us':>13} {'world.tick us':>14} {'overhead/module us':>19}")
    for n in (1, 5, 20):
        world = World(step="1ms", history=1000)
        for i in range(n):
            world.add_module(Counter(f"c{i}"))
        world.tick(1010)  # history full: each tick drops its oldest state
        mods = [world.modules[f"c{i}"] for i in range(n)]

        def bare(mods=mods) -> None:
            for k in range(ticks):
                for m in mods:
                    m.step(k, 1_000_000)

        t_bare, t_world = (t / ticks * 1e6 for t in best_of_each([bare, lambda w=world: w.tick(ticks)], 9))
        per = (t_world - t_bare) / n
        target = TARGETS.get(n)
        verdict = f"target <= {target}: {'met' if per <= target else 'MISSED'}" if target else ""
        print(f"   {n:>8} {t_bare:>13.3f} {t_world:>14.3f} {per:>19.3f}   {verdict}")
        if n == 1:  # where a tick of one module goes (timed apart: more loops in a round slow them all)
            fork = world.fork()
            fork.tick(1010)  # its history full, and its history entry's saver made
            t_tick, t_run, t_record, t_loop = (t / ticks * 1e6 for t in best_of_each(
                [lambda w=fork: w.tick(ticks), *overhead_parts(fork, ticks)], 9))
            run, record = t_run - t_loop, t_record - t_loop
            print(f"   {'':>8} a tick of one module, {t_tick:.3f} us: the generated tick (its step and the finite "
                  f"check) {run:.3f}, the history entry {record:.3f}, the rest (loop, events and observers "
                  f"checks) {t_tick - run - record:.3f}")
            fork.close()
        world.close()


def overhead_parts(world: World, ticks: int) -> list:
    """Loops that time the parts of a tick alone, on ``world`` (a fork: they leave it in no state to
    tick on): the bound generated tick (the module's step and the finite check), the history entry,
    and the empty loop they run in."""
    run, record, t0 = world.parts.context.run_tick, world.parts.context.record, world.tick_count

    def tick_alone() -> None:
        for k in range(t0, t0 + ticks):
            run(k, k)

    def record_alone() -> None:
        for k in range(t0, t0 + ticks):
            record(k)

    def loop_alone() -> None:
        for _k in range(t0, t0 + ticks):
            pass

    return [tick_alone, record_alone, loop_alone]


def box_scene(n_x: int = 20, n_y: int = 10, z: float = 0.05) -> SceneSpec:
    bodies = [BodySpec("floor", "plane", (), color=COLORS["grey"])]
    for i in range(n_x):
        for j in range(n_y):
            bodies.append(BodySpec(f"box_{i}_{j}", "box", (0.1, 0.1, 0.1), pos=(i * 0.2 - 2, j * 0.2 - 1, z),
                                   mass=0.2, color=COLORS["orange"]))
    return SceneSpec(bodies=tuple(bodies))


SELECTED = ["box_0_0", "box_5_5", "box_10_2", "box_15_7", "box_19_9"]


def physics_world(scene: SceneSpec, select: list[str] | None = None, others: str = "frozen",
                  keyframe_every: int = KEYFRAME_EVERY) -> World:
    from dynabrain.modules.mujoco.core import MujocoCore

    world = World("bench", step="2ms", history=200, core=MujocoCore("core", scene), keyframe_every=keyframe_every)
    if select is not None:
        world.make(select, others=others)
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


def history_costs(ticks: int = 200) -> None:
    print("2. history: snapshot per tick and backtick(1), against one physics step of 200 boxes")
    world = physics_world(box_scene())
    t_step = step_time(world)
    # what history costs a tick when it is full (each tick makes a state and drops the oldest): a world saving
    # a state every tick, against the same world whose history entry does nothing, interleaved
    every, none = physics_world(box_scene(), keyframe_every=1), physics_world(box_scene(), keyframe_every=1)
    for w in (every, none):
        w.tick(world.history.depth + 5)  # history full, its saver made
    none.parts.context.record = lambda _tick: None
    t_every, t_none = (t / ticks for t in best_of_each([lambda: every.tick(ticks), lambda: none.tick(ticks)], 9))
    t_snap = max(t_every - t_none, 0.0)
    t_made = best_of(lambda: [world.parts.timeline.capture() for _ in range(ticks)], 9) / ticks
    every.close()
    none.close()
    world.tick(5)

    def back_forth() -> None:  # back one, forward two: the tick moves on, so it lies anywhere between keyframes
        for _ in range(200):
            world.backtick(1)
            world.tick(2)

    t_pair = best_of(back_forth, 3) / 200
    t_tick = best_of(lambda: world.tick(400), 3) / 200  # two ticks
    t_back = max(t_pair - t_tick, 0.0)
    print(f"   physics step (200 boxes, all simulated): {t_step * 1e6:9.1f} us")
    print(f"   snapshot (whole-world state per tick):  {t_snap * 1e6:9.1f} us  ratio {t_snap / t_step:6.3f}"
          f"  target <= 0.05: {'met' if t_snap / t_step <= 0.05 else 'MISSED'}   (history full, a state every tick; "
          f"making one alone, {ticks} held at once: {t_made * 1e6:.1f} us)")
    print(f"   backtick(1):                            {t_back * 1e6:9.1f} us  ratio {t_back / t_step:6.3f}"
          f"  target <= 1.0: {'met' if t_back / t_step <= 1.0 else 'MISSED'}")
    print(f"   history: {world.history.describe()}")
    world.close()


SELECTION_TARGET = 35.0
"""Speed-up of 5 selected boxes (the others absent) over all 200 simulated, at least."""


def selection_speedup() -> None:
    print("3. selection: 200 resting boxes, all simulated vs 5 selected (the others frozen, or absent) vs a scene "
          "of only those 5")
    everything = physics_world(box_scene())
    frozen = physics_world(box_scene(), SELECTED)
    absent = physics_world(box_scene(), ["floor", *SELECTED], others="absent")  # (an absent floor holds nothing up)
    scene5 = SceneSpec(bodies=tuple(b for b in box_scene().bodies if b.name in ("floor", *SELECTED)))
    only5 = physics_world(scene5)
    worlds = (everything, frozen, absent, only5)
    t_all, t_frozen, t_absent, t_5 = (step_time(w) for w in worlds)
    ok = t_all / t_absent >= SELECTION_TARGET
    print(f"   all 200 simulated:            {t_all * 1e6:9.1f} us/step")
    print(f"   5 selected, others frozen:    {t_frozen * 1e6:9.1f} us/step   speed-up {t_all / t_frozen:6.1f}")
    print(f"   5 selected, others absent:    {t_absent * 1e6:9.1f} us/step   speed-up {t_all / t_absent:6.1f}  "
          f"target >= {SELECTION_TARGET:g}: {'met' if ok else 'MISSED'}")
    print(f"   scene of only 5:              {t_5 * 1e6:9.1f} us/step   speed-up {t_all / t_5:6.1f}  (MuJoCo's floor)")
    ngeom = frozen.core.mj.model.ngeom
    print(f"   frozen obstacles cost more: their {ngeom - 6} geoms stay in the model as static world geoms, and MuJoCo "
          "still does per-geom kinematics and collision (broad phase) for each every step; absent ones are not built")
    for w in worlds:
        w.close()


if __name__ == "__main__":
    kernel_overhead()
    history_costs()
    selection_speedup()
