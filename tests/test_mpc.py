"""Receding-horizon control on imagined futures (orchestrator/brain/mpc.py) on the swing with the humanoid
(real MuJoCo, the real servo and encoders): a short MPC run pumps the swing more than a zero-input plan;
the plan reaches the world through the PlanPlayer module, and a rollback restores it with the state; the
loop runs beside a world ticking in real time without blocking it; a logged run holds each replan's
chosen future on /imagined; a cost that raises names the replan's tick and leaves the world as it was;
bad controls are refused before anything runs."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.brain.mpc import Control, Mpc, MpcError
from dynabrain.orchestrator.logs.logger import McapLogger

ROOT = Path(__file__).resolve().parents[1]
SWING = ROOT / "scenarios" / "swing_mpc.yaml"
PIVOT = ["core.swing_pivot.q", "core.swing_pivot.qd"]
W2 = 9.81 / 0.85
"""The swing's natural frequency squared (1/s^2): the robot sits about 0.85 m under the pivot."""


def legs() -> dict[str, Control]:
    return {"hip": Control(["servo.l_hip_pitch.q_ref", "servo.r_hip_pitch.q_ref"], -1.2, 0.0),
            "knee": Control(["servo.l_knee.q_ref", "servo.r_knee.q_ref"], -1.5, 0.0)}


def swing_energy(f) -> np.ndarray:
    """Minus the swing's squared amplitude at the end of the horizon (the pendulum's phase-plane radius)."""
    q, qd = f["core.swing_pivot.q"][:, -1], f["core.swing_pivot.qd"][:, -1]
    return -(q ** 2 + qd ** 2 / W2)


def radius(world) -> float:
    return float(np.hypot(world.get("core.swing_pivot.q"), world.get("core.swing_pivot.qd") / np.sqrt(W2)))


@pytest.fixture()
def seated():
    world = load_world(SWING)
    world.tick(250)  # seated on the swing
    yield world
    world.close()


def test_mpc_pumps_the_swing_more_than_a_zero_input_plan(seated):
    idle = seated.fork()
    try:
        idle.tick(1000)
        still = radius(idle)
    finally:
        idle.close()
    with Mpc(seated, legs(), swing_energy, record=PIVOT, horizon="0.6s", knots=3, samples=8,
             backend="serial") as mpc:
        stats = mpc.run(seated, 1000, every="400ms")
    assert stats.replans == 5 and stats.ticks == 1000
    assert radius(seated) > 1.5 * still  # 0.074 against 0.041 (seed 0)
    left, right = seated.get("servo.l_hip_pitch.q_ref"), seated.get("servo.r_hip_pitch.q_ref")
    assert -1.2 <= left <= 0.0 and left == right  # the player drives both hips from one channel


def test_a_plan_is_part_of_the_state_a_rollback_plays_it_again(seated):
    with Mpc(seated, legs(), swing_energy, record=PIVOT, horizon="0.4s", knots=2, samples=4,
             backend="serial") as mpc:
        mpc.run(seated, 100, every="100ms")
        ahead = seated.fork()
        try:
            ahead.tick(50)  # on the last plan
            seated.backtick(30)  # back to a tick after the last replan: its plan is restored with the state
            seated.tick(80)
            for name in [*PIVOT, "servo.l_hip_pitch.q_ref", "mpc.knee"]:
                assert np.asarray(seated.get(name)).tobytes() == np.asarray(ahead.get(name)).tobytes(), name
        finally:
            ahead.close()


def test_mpc_beside_a_world_ticking_in_real_time(seated):
    mpc = Mpc(seated, legs(), swing_energy, record=PIVOT, horizon="0.2s", knots=2, samples=4, backend="serial")
    try:
        mpc.start(seated, every="50ms")
        ticks0 = seated.tick_count
        while mpc.stats.replans < 3:
            seated.wait(0.05)
        stats = mpc.stop()
        assert seated.running and seated.tick_count > ticks0  # the world kept ticking meanwhile
        assert stats.replans >= 3 and "replans" in stats.summary()
        assert len(seated.get("mpc.plan")) > 0
    finally:
        seated.stop()
        mpc.close()


def test_a_logged_mpc_run_holds_its_imagined_futures(seated, tmp_path):
    log = tmp_path / "mpc.mcap"
    logger = McapLogger(log).attach(seated)
    with Mpc(seated, legs(), swing_energy, record=PIVOT, horizon="0.2s", knots=2, samples=4,
             backend="serial", name="pump") as mpc:
        mpc.run(seated, 150, every="100ms")
    logger.close()
    with log.open("rb") as fh:
        topics = {c.topic for c in make_reader(fh).get_summary().channels.values()}
    assert any(t.startswith("/imagined/pump/0/") for t in topics), sorted(topics)


def test_a_cost_that_raises_names_the_tick_and_leaves_the_world_as_it_was(seated):
    def broken(f):
        raise ValueError("no such thing")

    mpc = Mpc(seated, legs(), broken, record=PIVOT, horizon="0.1s", knots=2, samples=2, backend="serial")
    try:
        before = seated.export_state()
        with pytest.raises(MpcError, match=r"cost function raised at the replan of tick 250: ValueError: no such"):
            mpc.run(seated, 50)
        assert seated.export_state() == before
        mpc.cost = lambda f: np.zeros(3)
        with pytest.raises(MpcError, match=r"returned shape \(3,\) at the replan of tick 250"):
            mpc.replan()
        mpc.cost = lambda f: np.where(np.arange(2) == 0, np.nan, 1.0)  # a sample that diverged: infinite cost
        assert np.isinf(mpc.replan().costs[0])
    finally:
        mpc.close()


def test_bad_controls_are_refused_before_anything_runs(seated):
    with pytest.raises(MpcError, match=r"controls\['hip'\].*servo.l_hip_pich.q_ref"):
        Mpc(seated, {"hip": Control(["servo.l_hip_pich.q_ref"], -1, 0)}, swing_energy, backend="serial")
    with pytest.raises(MpcError, match=r"'servo.kp' is a parameter"):
        Mpc(seated, {"hip": Control(["servo.kp"], -1, 0)}, swing_energy, backend="serial")
    with pytest.raises(MpcError, match=r"bounds 0 .. -1"):
        Mpc(seated, {"hip": Control(["servo.l_hip_pitch.q_ref"], 0, -1)}, swing_energy, backend="serial")
    with pytest.raises(MpcError, match=r"record: .*core.swing_pivt.q"):
        Mpc(seated, legs(), swing_energy, record=["core.swing_pivt.q"], backend="serial")
    with pytest.raises(MpcError, match=r"method 'ilqr' is unknown"):
        Mpc(seated, legs(), swing_energy, method="ilqr", backend="serial")
    with pytest.raises(MpcError, match=r"horizon is '1 parsec'"):
        Mpc(seated, legs(), swing_energy, horizon="1 parsec", backend="serial")
    assert "mpc" not in seated.modules  # nothing was added


def test_mpc_of_a_world_served_over_zenoh():
    from dynabrain.bridge.mpc import RemoteMpc
    from dynabrain.bridge.testing import serving

    world = load_world(SWING)
    world.tick(250)
    with serving(world, "swing_mpc") as (server, brain):
        brain.acquire()
        mpc = RemoteMpc(brain, legs(), swing_energy, record=PIVOT, horizon="0.2s", knots=2, samples=4,
                        method="sampling")
        stats = mpc.run(duration=100, every="100ms")
        assert stats.replans == 2 and server.world.tick_count == 350
        assert "mpc" in server.world.modules and len(server.world.get("mpc.plan")) == 100
        assert [tick for tick, _ in mpc.futures] == [250, 300]
        # the served world played the future the brain chose: 50 ticks into it, where it predicted, bit for bit
        predicted = mpc.futures[-1][1]["core.swing_pivot.q"][49]
        assert np.asarray(server.world.get("core.swing_pivot.q")).tobytes() == np.asarray(predicted).tobytes()
        with pytest.raises(MpcError, match=r"controls\['hip'\]"):
            RemoteMpc(brain, {"hip": Control(["servo.nothing.q_ref"], -1, 0)}, swing_energy)


def test_futures_hold_what_the_brain_assumes_of_inputs_it_does_not_control(seated):
    mpc = Mpc(seated, legs(), swing_energy, record=[*PIVOT, "servo.l_elbow.q_ref"], horizon="0.1s", knots=2,
              samples=2, backend="serial", assume={"servo.l_elbow.q_ref": 0.5})
    try:
        plan = mpc.replan()
        assert np.all(plan.signals["servo.l_elbow.q_ref"] == 0.5) and seated.get("servo.l_elbow.q_ref") == 0.0
    finally:
        mpc.close()
    with pytest.raises(MpcError, match=r"assume\['servo.l_elbow.q_ref'\] has shape \(2,\)"):
        Mpc(seated, legs(), swing_energy, backend="serial", assume={"servo.l_elbow.q_ref": [0.0, 0.0]})
    with pytest.raises(MpcError, match=r"assume: 'servo.kp' is a parameter"):
        Mpc(seated, legs(), swing_energy, backend="serial", assume={"servo.kp": 1.0})


def test_remote_mpc_replans_while_the_served_world_runs_in_real_time():
    from dynabrain.bridge.mpc import RemoteMpc
    from dynabrain.bridge.testing import serving

    world = load_world(SWING)
    with serving(world, "swing_mpc") as (server, brain):
        brain.acquire()
        mpc = RemoteMpc(brain, legs(), swing_energy, record=PIVOT, horizon="0.1s", knots=2, samples=2,
                        method="sampling")
        mpc.start(every="100ms")  # starts the served loop at real time
        deadline = time.monotonic() + 30
        while mpc.stats.replans < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        stats = mpc.stop()
        brain.stop()
        assert stats.replans >= 3 and "mpc" in server.world.modules
        ticks = [tick for tick, _ in mpc.futures]  # where each plan takes over: its state's tick and its delay
        assert len(set(ticks)) == len(ticks) and min(ticks[1:]) > ticks[0]  # from later states of the running world
        assert stats.ticks == 0 and server.world.tick_count > ticks[0]  # the world ran by itself, in real time


def test_mpc_keeps_the_humanoid_up_on_the_fast_earthquake_where_the_servo_falls():
    """The paper's fast floor (10 degrees at 1 Hz, 4 cm at 2 Hz, `scenarios/balance_quake.yaml`): the servo
    alone lets the kid fall within 1.5 s of the floor joining; the brain, imagining 16 futures of 0.5 s
    (the floor with them) every 50 ms on the ankle and hip pitch, keeps it standing over the same time.
    Its futures run in lockstep, so the outcome is the same on any machine."""
    import sys

    sys.path.insert(0, str(ROOT / "examples"))
    import balance_mpc as bm

    fell, _ = bm.quake_trial(10.0, 0.04, "servo", 1.5)
    assert fell is not None and fell <= 2.5
    fell, said = bm.quake_trial(10.0, 0.04, "mpc", 1.5, futures=(16, 0.5, 0.05))
    assert fell is None, said
    assert "30 replans" in said


def test_a_replan_whose_every_future_fails_says_why_and_a_rebuilt_quake_world_imports():
    """Every future failing is an error naming the first failure (not a plan of infinite cost). And a
    world whose floor joined by an event (its selection changed first) runs on the processes backend,
    which rebuilds it and imports the state: the moving floor is set up for the state's selection."""
    import sys

    sys.path.insert(0, str(ROOT / "examples"))
    import balance_mpc as bm

    from dynabrain.orchestrator import Batch

    world = bm.quake_world(10.0, 0.04, stabilizer=False)
    try:
        with Batch(world, backend="processes", workers=1) as batch:
            rebuilt = batch.run(15, branches=1, record=["core.pelvis.pos"])
        with Batch(world, backend="lockstep") as batch:
            forked = batch.run(15, branches=1, record=["core.pelvis.pos"])
        assert rebuilt.ok and np.array_equal(rebuilt.branch("core.pelvis.pos", 0), forked.branch("core.pelvis.pos", 0))
        diverging = {"core.pelvis.wrench": [1e30] * 6}  # (every future diverges)
        with (Mpc(world, bm.pitch_strategies(), bm.quake_cost, record=bm.QUAKE_RECORD, horizon=0.1, samples=4,
                  backend="serial", assume=diverging) as mpc,
              pytest.raises(MpcError, match=r"every future of the replan of tick \d+ failed; the first: ")):
            mpc.replan()
    finally:
        world.close()
