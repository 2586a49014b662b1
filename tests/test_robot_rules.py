"""Brain-side and non-physical modules: the stabilizer's law, the leg reflexes, the cycle meter (pure
logic, driven through the bus), and the breakout rules on the real core: blocks disappear when the
ball leaves them, come back on rollback, and the game is won."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.breakout import BreakoutRules, Paddle
from dynabrain.modules.cycles import CycleMeter
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.reflexes import ContactKick, PhasePump
from dynabrain.modules.stabilizer import Stabilizer
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.world import World

MODELS = Path(__file__).resolve().parent.parent / "scenarios" / "models"


def signal_world(module, step: str = "10ms") -> World:
    world = World("logic", step=step, history=100)
    world.add_module(module)
    return world


def test_stabilizer_leans_against_the_zmp_error_and_holds_when_airborne():
    world = signal_world(Stabilizer("stab", ki=8.0, filter="0.2s", max_angle="10deg"))
    world.set("stab.center", [0.01, 0.0, 0.0])
    world.set("stab.zmp", [0.03, -0.01, 0.0])  # ahead of and right of the centre
    world.tick(1)
    a = 0.01 / 0.21  # first-order filter step, then the integral's first step
    assert world.get("stab.pitch") == pytest.approx(8.0 * a * 0.02 * 0.01, rel=1e-9)
    world.tick(49)
    pitch, roll = world.get("stab.pitch"), world.get("stab.roll")
    assert pitch > 0 and roll > 0  # ahead: lean back (positive pitch); right: lean left (positive roll)
    assert pitch == pytest.approx(2 * roll, rel=0.01)  # proportional to the error, each axis
    world.tick(2000)
    assert world.get("stab.pitch") == pytest.approx(math.radians(10))  # clamped
    held = world.get("stab.pitch")
    world.set("stab.zmp", [np.nan] * 3)  # no foot loaded: hold
    world.tick(50)
    assert world.get("stab.pitch") == held
    world.set("stab.heading", math.pi)  # facing -x: the same world error is the other way round
    world.set("stab.zmp", [-0.01, 0.0, 0.0])
    world.tick(3000)
    assert world.get("stab.pitch") == pytest.approx(math.radians(10))
    world.close()


def test_contact_kick_kicks_rests_and_waits_for_the_next_contact():
    world = signal_world(ContactKick("kick", hip_offset="40deg", knee_offset="-60deg", duration="0.1s", rest="0.2s",
                                     threshold=5), step="10ms")
    world.tick(5)
    assert world.get("kick.hip") == 0 and world.get("kick.kicks") == 0
    world.set("kick.force", [0.0, 0.0, -20.0])
    world.tick(1)
    assert world.get("kick.hip") == pytest.approx(math.radians(40)) and world.get("kick.knee") < 0
    world.tick(10)  # 0.1 s of kicking
    assert world.get("kick.hip") == 0
    world.tick(19)  # resting: the contact is ignored
    assert world.get("kick.kicks") == 1 and world.get("kick.hip") == 0
    world.tick(2)
    assert world.get("kick.kicks") == 2  # ready again, and the foot is still down
    world.close()


def test_phase_pump_follows_the_swing_rate_at_a_limited_speed():
    world = signal_world(PhasePump("pump", hip_amplitude="-60deg", knee_amplitude="-80deg", rate_scale=0.05, speed=2.0))
    world.set("pump.rate", 1.0)
    world.tick(1)
    reach = 2.0 * 0.01 / math.radians(80)
    assert world.get("pump.knee") == pytest.approx(math.radians(-80) * reach)
    world.tick(100)
    assert world.get("pump.hip") == pytest.approx(math.radians(-60) * math.tanh(20), rel=1e-9)
    world.set("pump.rate", -1.0)
    world.tick(200)
    assert world.get("pump.hip") == pytest.approx(math.radians(60) * math.tanh(20), rel=1e-9)
    world.close()


def test_cycle_meter_measures_a_drifting_growing_oscillation():
    world = signal_world(CycleMeter("meter", unit="rad", deadband=0.01), step="10ms")
    for k in range(1, 1001):  # 10 s of a 0.5 Hz sine growing from 0.1 to 0.2, on a drifting mean
        t = k * 0.01
        world.set("meter.x", 0.005 * t + (0.1 + 0.01 * t) * math.sin(math.pi * t))
        world.tick()
    assert world.get("meter.cycles") == 4  # 5 periods, minus the motion before the first turning point
    peaks = world.get("meter.peaks")
    swings = int(world.get("meter.swings"))
    assert swings == 9 and np.isnan(peaks[swings:]).all()
    assert np.all(np.diff(peaks[:swings]) > 0)  # growing
    assert peaks[4] == pytest.approx(0.1 + 0.01 * 5.5, abs=0.01)  # the swing centred on t = 5.5 s
    world.close()


@pytest.mark.parametrize("make", [
    lambda: Stabilizer("stab"), lambda: ContactKick("kick", threshold=0.1), lambda: PhasePump("pump"),
    lambda: CycleMeter("meter", deadband=0.001)], ids=["stabilizer", "kick", "pump", "meter"])
def test_rule_modules_pass_check_module(make):
    check_module(make(), step="10ms").assert_ok()


def breakout_world(history: int = 3000) -> World:
    core = MujocoCore("core", SceneSpec(model=str(MODELS / "breakout.xml")), friction=0.0, restitution=1.0,
                      substeps=4)
    world = World("breakout", step="2ms", history=history, core=core)
    world.add_module(BreakoutRules("rules", targets=["block_*"]))
    world.add_module(Paddle("player"), connect=[
        ("core.ball.pos", "player.ball_pos"), ("core.ball.linvel", "player.ball_vel"),
        ("core.paddle_x.q", "player.paddle_q"), ("core.paddle_x.qd", "player.paddle_qd"),
        ("rules.aim", "player.aim"), ("player.paddle_force", "core.paddle_x.force"),
        ("player.serve_x", "core.ball_x.force"), ("player.serve_y", "core.ball_y.force")])
    return world


def test_a_block_disappears_after_the_ball_bounces_off_it_and_comes_back_on_rollback():
    world = breakout_world()
    model = lambda: world.core.mj.model  # noqa: E731 - the core's current compiled model
    n = 0
    while world.get("rules.remaining") == 18:
        world.tick()
        n += 1
        assert n < 2000, "no block hit in 4 s"
    gone = int(np.flatnonzero(world.get("rules.alive") == 0)[0])
    block = world.modules["rules"].blocks[gone]
    geom = model().geom(block).id
    assert model().geom_contype[geom] == 0 and model().geom_rgba[geom, 3] == 0
    assert world.core.body_velocity("ball")[0][1] < 0  # the ball bounced back
    after = world.snapshot()
    world.tick(300)
    world.backtick(301)  # just before the block went
    assert world.get("rules.remaining") == 18 and model().geom_contype[geom] == 1 and model().geom_rgba[geom, 3] == 1
    world.tick(1)
    assert np.array_equal(world.snapshot().bus, after.bus)  # and it goes again, exactly
    world.close()


def test_the_player_wins_the_game():
    world = breakout_world(history=10)
    world.tick(round(25 / 0.002))
    assert world.get("rules.won") == 1 and world.get("rules.hits") == 18
    assert all(model_alpha == 0 for model_alpha in world.core.mj.model.geom_rgba[
        [world.core.mj.model.geom(b).id for b in world.modules["rules"].blocks], 3])
    world.close()


def test_breakout_modules_pass_check_module():
    core = MujocoCore("core", SceneSpec(model=str(MODELS / "breakout.xml")), friction=0.0, restitution=1.0)
    check_module(BreakoutRules("rules", targets=["block_0_*"]), core=core).assert_ok()
    check_module(Paddle("player")).assert_ok()
