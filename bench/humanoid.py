"""Humanoid benchmark: the orchestrated robot against a raw MuJoCo loop doing the same work, in one run.

The world: the humanoid "kid" (23 motors, 29 DoF) standing on the earthquake floor (2 more DoF),
with encoders, the servo (PD, torque limits, an angle-vector program), force/torque sensors at both
ankles, an accelerometer, a gyro, the ZMP sensor (every 10 ms) and the moving floor, all through the
kernel: the bus, the schedule, history on at the default depth (1000 ticks), twice: as a World keeps
it by default (a keyframe every `KEYFRAMES` = 2 ticks, `World(keyframe_every=...)`: the ticks between
are stepped again when a backtick goes to one), and with a state saved every tick (``keyframe_every=1``).

The baseline: one `mj_step` per tick of the same compiled model, with the same PD control, the same
floor drive and the same sensor reads computed inline in a Python loop (the ZMP with the same
functions, every 10 ms), and nothing else.

Printed: the step times (mj_step alone, the raw loop, both worlds, interleaved best of 7), the ratios
orchestrated / raw (target: at most 1.10), the real-time factor, the paper's figure for scale (EusDyna
on ODE: 0.74 s of computing per simulated second of a humanoid); what a backtick(1) costs either way
(the trade keyframes make); and where an orchestrated tick goes: each module's step, the history
entry and its parts, the finite-output check, and the rest of the kernel.

Run: ``.venv/bin/python bench/humanoid.py``
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
from timing import best_of_each

from dynabrain.modules.floor import TWO_PI, MovingFloor, wave
from dynabrain.modules.mujoco.core import STATE, MujocoCore
from dynabrain.modules.sensors import Accelerometer, Encoders, ForceSensor, Gyro
from dynabrain.modules.servo import Servo
from dynabrain.modules.support import feet_support
from dynabrain.modules.zmp import ZmpSensor
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.structure import build_structure
from dynabrain.orchestrator.kernel.world import KEYFRAME_EVERY, World

MODEL = Path(__file__).resolve().parent.parent / "scenarios" / "models" / "earthquake.xml"
POSE = {"l_hip_pitch": -15, "r_hip_pitch": -15, "l_knee": 30, "r_knee": 30, "l_ankle_pitch": -15,
        "r_ankle_pitch": -15, "l_shoulder_roll": 10, "r_shoulder_roll": -10, "l_elbow": -30, "r_elbow": -30}
FLOOR = {"amplitude": 0.01, "frequency": 0.3, "tilt_amplitude": math.radians(3), "tilt_frequency": 0.2, "ramp": 1.0}
ZMP_EVERY = 10e-3
HISTORY = 1000  # ticks of history kept (the World default)
KEYFRAMES = KEYFRAME_EVERY  # the default world's `keyframe_every`
TARGET = 1.10


def orchestrated(step: str, keyframe_every: int = KEYFRAMES) -> World:
    """The world of the benchmark, settled for a second."""
    core = MujocoCore("core", SceneSpec(model=str(MODEL)), friction=1.0)
    world = World("bench", step=step, history=HISTORY, core=core, keyframe_every=keyframe_every)
    world.add_module(Encoders("enc"))
    world.add_module(Servo("servo", sequence=[{"pose": POSE, "duration": "0.5s"}]),
                     connect=[("enc.q", "servo.q"), ("enc.qd", "servo.qd"), ("servo.ctrl", "core.ctrl")])
    for side in ("l", "r"):
        world.add_module(ForceSensor(f"{side}_ft", targets=[f"{side}_foot_ft"]))
    world.add_module(Accelerometer("acc", targets=["imu"]))
    world.add_module(Gyro("gyro", targets=["imu"]))
    world.add_module(ZmpSensor("zmp", targets=["l_foot", "r_foot"]), period=round(ZMP_EVERY * 1e9))
    world.add_module(MovingFloor("quake", **FLOOR), connect=[
        ("core.floor_slide.q", "quake.q"), ("core.floor_slide.qd", "quake.qd"),
        ("quake.force", "core.floor_slide.force"),
        ("core.floor_tilt.q", "quake.tilt_q"), ("core.floor_tilt.qd", "quake.tilt_qd"),
        ("quake.tilt_torque", "core.floor_tilt.force")])
    world.tick(round(1.0 / (world.dt_ns * 1e-9)))
    return world


class RawLoop:
    """The same work as the orchestrated world, inline around `mj_step` (no kernel, no history)."""

    def __init__(self, world: World):
        core, servo = world.core, world.modules["servo"]
        self.m = copy.deepcopy(core.mj.model)  # the very model the core compiled (options, contacts)
        self.d = mujoco.MjData(self.m)
        mujoco.mj_setState(self.m, self.d, core.get_state()[1], STATE)
        m = self.m
        self.dt = m.opt.timestep
        jid = [m.joint(j).id for j in servo.joints]
        self.qadr, self.dadr = m.jnt_qposadr[jid], m.jnt_dofadr[jid]
        self.motion, self.t0 = servo._motion, servo._t0
        self.kp, self.kd, self.limit = servo.params["kp"], servo.params["kd"], servo.params["tau_max"]
        self.floor = [m.jnt_dofadr[m.joint(j).id] for j in ("floor_slide", "floor_tilt")]
        self.floor_q = [m.jnt_qposadr[m.joint(j).id] for j in ("floor_slide", "floor_tilt")]
        quake = world.modules["quake"]
        self.envelope, *self.phase = quake.get_state()
        self.floor_params = dict(quake.params)
        adr = {m.sensor(i).name: int(m.sensor_adr[i]) for i in range(m.nsensor)}
        self.ft = np.array([np.r_[adr[f"{s}_foot_force"]:adr[f"{s}_foot_force"] + 3,
                                  adr[f"{s}_foot_torque"]:adr[f"{s}_foot_torque"] + 3] for s in "lr"])
        self.acc, self.gyro = np.r_[adr["imu_acc"]:adr["imu_acc"] + 3], np.r_[adr["imu_gyro"]:adr["imu_gyro"] + 3]
        zmp = world.modules["zmp"]
        self.zmp_index, self.zmp_nums = zmp._index, zmp._nums
        self.zmp_every = round(ZMP_EVERY / self.dt)
        self.t_ns = world.time_ns

    def run(self, ticks: int) -> None:
        m, d = self.m, self.d
        dt_ns = round(self.dt * 1e9)
        for k in range(ticks):
            q, qd = d.qpos[self.qadr], d.qvel[self.dadr]  # encoders
            pos, rate = self.motion.at(self.t_ns - self.t0)  # servo
            d.ctrl[:] = np.clip(self.kp * (pos - q) + self.kd * (rate - qd), -self.limit, self.limit)
            self._floor()
            mujoco.mj_step(m, d)
            self.t_ns += dt_ns
            _wrench, _acc, _gyro = d.sensordata[self.ft], d.sensordata[self.acc], d.sensordata[self.gyro]  # sensors
            if k % self.zmp_every == 0:
                self._zmp()

    def _floor(self) -> None:
        """The moving floor's law (see modules/floor.py), inline: envelope, phases, PD + feedforward."""
        d, p, h = self.d, self.floor_params, self.dt
        rate = 1.0 / p["ramp"] if self.envelope < 1.0 else 0.0
        self.envelope = min(self.envelope + rate * h, 1.0)
        de = rate if self.envelope < 1.0 else 0.0
        for i, (amp, freq, kp, kd, inertia) in enumerate((("amplitude", "frequency", "kp", "kd", "mass"),
                                                          ("tilt_amplitude", "tilt_frequency", "tilt_kp", "tilt_kd",
                                                           "inertia"))):
            self.phase[i] = math.fmod(self.phase[i] + TWO_PI * p[freq] * h, TWO_PI)
            x, v, a = wave(p[amp], TWO_PI * p[freq], self.phase[i], self.envelope, de)
            qa, da = self.floor_q[i], self.floor[i]
            d.qfrc_applied[da] = p[kp] * (x - d.qpos[qa]) + p[kd] * (v - d.qvel[da]) + p[inertia] * a

    def _zmp(self) -> None:
        """The ZMP sensor's computation (see modules/zmp.py), inline: the feet's contact sensors read in
        one gather, and every value it outputs computed by the same function."""
        feet_support(self.d.sensordata[self.zmp_index].tolist(), self.zmp_nums, 1.0, 0.0)


def measure(step: str, ticks: int = 1000) -> None:
    world, keyed = orchestrated(step, 1), orchestrated(step, KEYFRAMES)
    raw, bare = RawLoop(world), RawLoop(world)
    dt = world.dt_ns * 1e-9
    nv = raw.m.nv

    bare.d.ctrl[:] = world.get("servo.ctrl")  # the servo's torques now, held: the robot stays as it stands
    standing = np.empty(mujoco.mj_stateSize(bare.m, STATE))
    mujoco.mj_getState(bare.m, bare.d, standing, STATE)

    def step_only() -> None:  # back to the standing state every 100 steps, before the pose drifts
        for k in range(ticks):
            if k % 100 == 0:
                mujoco.mj_setState(bare.m, bare.d, standing, STATE)
            mujoco.mj_step(bare.m, bare.d)

    t_step, t_raw, t_world, t_keyed = (t / ticks for t in best_of_each(
        [step_only, lambda: raw.run(ticks), lambda: world.tick(ticks), lambda: keyed.tick(ticks)]))
    standing = world.core.body_pose("pelvis")[0][2] > 0.25 and keyed.core.body_pose("pelvis")[0][2] > 0.25
    print(f"   step {step} ({nv} DoF, {raw.m.nu} motors, {raw.d.ncon} contacts), "
          f"robot {'standing' if standing else 'FALLEN'}:")
    print(f"     mj_step alone (same stance):      {t_step * 1e6:8.1f} us")
    print(f"     raw loop (same work, inline):     {t_raw * 1e6:8.1f} us")
    for label, t_tick in ((f"default (keyframes every {KEYFRAMES})", t_keyed), ("a state every tick", t_world)):
        ratio = t_tick / t_raw
        verdict = (f"target <= {TARGET}: {'met' if ratio <= TARGET else 'MISSED'}" if t_tick is t_keyed
                   else "(for comparison: the target is the default world's)")
        print(f"     orchestrated, {label + ':':<31}{t_tick * 1e6:6.1f} us   ratio / raw {ratio:5.3f}   {verdict}")
    print(f"     real-time factor: orchestrated {dt / t_keyed:6.1f}, raw {dt / t_raw:6.1f}; computing per "
          f"simulated second: {t_keyed / dt:.3f} s (paper: 0.74 s)")
    backtick_trade(world, keyed)
    breakdown(world, ticks)
    print(f"     history every tick costs {(t_world - t_keyed) * 1e6:.1f} us a tick more than keyframes every "
          f"{KEYFRAMES} ticks (the capture, and keeping 1000 states: memory a tick touches and frees)")
    world.close()
    keyed.close()


def backtick_trade(world: World, keyed: World, rounds: int = 40) -> None:
    """What ``backtick(1)`` costs in each world, on average over where the tick lies between keyframes
    (each round goes back one tick and forward two, so the tick moves on): the round's time less two
    ticks' (timed alike, interleaved). Keyframes every k ticks step up to k - 1 ticks again."""
    def rounds_of(w: World) -> Callable[[], None]:
        def run() -> None:
            for _ in range(rounds):
                w.backtick(1)
                w.tick(2)
        return run

    def ticks_of(w: World) -> Callable[[], None]:
        return lambda: w.tick(2 * rounds)

    r_world, r_keyed, t_world, t_keyed = (t / rounds for t in best_of_each(
        [rounds_of(world), rounds_of(keyed), ticks_of(world), ticks_of(keyed)]))
    back = r_world - t_world  # restoring a state (the core's set_state steps MuJoCo's first half again)
    print(f"     backtick(1): {back * 1e6:6.1f} us with a state every tick, {(r_keyed - t_keyed) * 1e6:6.1f} us with "
          f"keyframes every {KEYFRAMES} (on average; up to {KEYFRAMES - 1} ticks stepped again: about "
          f"{(back + (KEYFRAMES - 1) * t_keyed / 2) * 1e6:.0f} us at worst)")


def breakdown(world: World, ticks: int, repeats: int = 5) -> None:
    """Where an orchestrated tick goes: each module's step (per tick, on average) and the rest (the
    kernel's dispatch, bus copies, the finite-output check and the history entry), timed on a fork of
    the world (best of ``repeats``; the timers add about 0.1 us per module); then the history entry,
    its parts and the finite check, each timed alone on the fork (hot in the cache: in the run, a state
    every tick costs more, see the last line)."""
    fork = world.fork()
    fork.tick(100)  # the fork's modules find their ids in the copied core
    clock = time.perf_counter
    spent: dict[str, float] = {}
    for name, module in fork.modules.items():
        def timed(t_ns, dt_ns, _step=module.step, _name=name):
            t0 = clock()
            _step(t_ns, dt_ns)
            spent[_name] += clock() - t0
        module.step = timed
    # the kernel binds each module's step when it builds the schedule: rebuild it with the timers
    fork.parts.context.install(build_structure(fork.structure.records, fork.structure.connections), carry_values=True)
    best: tuple[float, dict[str, float]] = (float("inf"), {})
    for _ in range(repeats):
        spent.update(dict.fromkeys(fork.modules, 0.0))
        t0 = clock()
        fork.tick(ticks)
        total = clock() - t0
        if total < best[0]:
            best = (total, dict(spent))
    total, parts = best
    shown = ", ".join(f"{name} {t / ticks * 1e6:.1f}" for name, t in parts.items())
    print(f"     per tick (us): {shown}; kernel + history {(total - sum(parts.values())) / ticks * 1e6:.1f}")
    groups = [", ".join(m.name for m in f.members) for f in world.structure.compiled._fused.values()]
    if groups:
        print(f"     (timed one by one; the world steps {'; '.join(groups)} as one call: `Module.fuse`)")
    record, get_state, bus_bytes = fork.parts.context.record, fork.core.get_state, fork.parts.context.mv.tobytes
    probes = fork.structure.output_check.probes(fork.parts.context.buf, fork.parts.context.mv)
    t0 = fork.tick_count

    def entries() -> None:
        for k in range(t0, t0 + ticks):
            record(k)

    def core_states() -> None:
        for _ in range(ticks):
            get_state()

    def buses() -> None:
        for _ in range(ticks):
            bus_bytes()

    def checks() -> None:
        for _ in range(ticks):
            for add, values in probes:
                add(values)

    t_entry, t_core, t_bus, t_check = (t / ticks * 1e6 for t in best_of_each([entries, core_states, buses, checks]))
    print(f"     alone (us): history entry {t_entry:.1f} (the core's get_state {t_core:.1f}, the bus's bytes "
          f"{t_bus:.1f}), finite-output check {t_check:.1f} ({sum(v.nbytes for _a, v in probes) // 8} values)")
    fork.close()


def main() -> None:
    print("humanoid: orchestrated world against a raw MuJoCo loop doing the same work, in one run")
    for step in ("2ms", "5ms"):
        measure(step)


if __name__ == "__main__":
    main()
