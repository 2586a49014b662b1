"""The kitchen tray by the humanoid (the paper's Fig. 12): the kid's motion program, from whole-body IK.

The kid (scenarios/models/kid.xml) stands at the kitchen's work board (scenarios/models/kitchen.xml).
For each dish a hand goes above it, down onto it, takes it (a run-time weld: the grasp), lifts it,
carries it over the tray, lowers it onto the stack there and lets go (the weld is removed); the right
hand takes the two dishes on its side, the left hand the two on its own. Then both hands take the tray
by its side rims, lift it, carry it along the board to the left, set it down and let go.

The poses of the dishes' part are the whole-body IK's (`modules.whole_body`): hand-tip targets with the
feet planted and the centre of mass over the soles, each solve starting from the pose before. A hand
takes a dish with the tilt it will have where it sets it down (solved first: the world's vertical in
the hand's frame, `Planner.upright`), and keeps it there, so that the dish lands level. The tray is
taken in an IK pose too, then lifted by both shoulders turning up alike and carried by the waist
turning (`Planner.turn`): both move the two hands as one rigid body, as the welds to the tray hold them,
which no IK pose of two hands with free wrists would keep. The servo plays the poses as its timed
``sequence``; the grasps and releases are scenario events at the times the poses end.

A grasp is welds through a thin "grip" body that the brain adds inside what it takes (a dish, the
tray's floor): hand to grip, grip to what it holds (both hands to one grip for the tray). Letting go
removes the grip (`remove_body`), and its welds go with it: scenario events can make a joint
(`make_joint`) but not remove one, so the grip is the handle by which an event lets go.

    .venv/bin/python examples/kitchen_tray.py            # plan, run scenarios/kitchen_tray.yaml, check it
    .venv/bin/python examples/kitchen_tray.py --yaml     # print the program (servo sequence and events)
    .venv/bin/python examples/kitchen_tray.py --write    # write it into scenarios/kitchen_tray.yaml

`scenarios/kitchen_tray.yaml` holds the program this prints (tests/test_paper_scenes.py checks they agree).
"""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import yaml

from dynabrain.modules.ik import Target
from dynabrain.modules.whole_body import WholeBody, WholeBodyResult
from dynabrain.orchestrator import World, load_scenario
from dynabrain.orchestrator.scenario.runner import run_scenario

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "kitchen_tray.yaml"
CROUCH = {"l_hip_pitch": -15, "r_hip_pitch": -15, "l_knee": 30, "r_knee": 30, "l_ankle_pitch": -15,
          "r_ankle_pitch": -15, "l_shoulder_pitch": 35, "r_shoulder_pitch": 35, "l_shoulder_roll": 10,
          "r_shoulder_roll": -10, "l_elbow": -110, "r_elbow": -110}
"""The pose the kid takes first (degrees), in ``CROUCH_S``: humanoid_stand's crouch with the forearms
raised and drawn back, so that the hands come up beside the board's edge, not under it; it then stands
still for ``SETTLE_S`` before the program solved from there starts."""
CROUCH_S, SETTLE_S = 0.5, 0.3
HANDS = {"r": "r_hand", "l": "l_hand"}
"""Hand -> the body a grasp welds (its tip is the site ``<hand>_tip``)."""
SIDES = {"r": "right", "l": "left"}
DISHES = (("dish_0", "r"), ("dish_1", "r"), ("dish_2", "l"), ("dish_3", "l"))
"""The dishes in the order they are stacked, with the hand that takes each."""
UP = np.array([0.0, 0.0, 1.0])
DISH_GRIP = {"cylinder": {"size": ["20mm", "3mm"], "mass": "10g"}}
TRAY_GRIP = {"box": {"size": ["100mm", "140mm", "4mm"], "mass": "20g"}}
"""The grips: thin shapes inside a dish and inside the tray's floor (a dish lies 8 mm thick, the floor
6 mm), touching nothing. Not a small sphere: a weld through a body of almost no rotational inertia is
soft about its turns (the tray turned 10 degrees in the hands through a 2 mm sphere of 20 g)."""
FAR_M = 0.002
"""How far a hand may stay from its target when the IK cannot bring it within its default 1 mm."""


@dataclass(frozen=True)
class Motions:
    """Heights (m) and durations (s) of the program."""

    gap_m: float = 0.001
    """A hand tip takes hold this far above what it holds (it is welded where it stands)."""
    above_m: float = 0.045
    """A hand comes down onto a dish from this far above."""
    clear_m: float = 0.003
    """A dish, or the tray, is let go this far above where it comes to rest."""
    lift_deg: float = 8.0
    """How far both shoulders turn up to lift the tray (about 3 cm, the tray tilted as much)."""
    turn_deg: float = 25.0
    """How far the waist turns to carry the tray along the board, to the left."""
    reach_s: float = 0.6
    down_s: float = 0.4
    hold_s: float = 0.2
    lift_s: float = 0.4
    over_s: float = 0.7
    carry_s: float = 1.2
    back_s: float = 0.8


@dataclass
class Program:
    """The servo's ``sequence`` (after the crouch) and the events at the times its steps end."""

    steps: list[dict] = field(default_factory=list)
    """``{name, pose: {joint: degrees}, duration_s}``; an empty pose holds the one before."""
    events: list[dict] = field(default_factory=list)
    """Scenario events (``at`` in s)."""
    t_s: float = CROUCH_S + SETTLE_S

    def sequence(self) -> list[dict]:
        """The servo's whole ``sequence`` parameter: the crouch, standing still, then the program."""
        head = [{"pose": dict(CROUCH), "duration": f"{CROUCH_S:g}s"}, {"pose": {}, "duration": f"{SETTLE_S:g}s"}]
        return head + [{"pose": s["pose"], "duration": f"{s['duration_s']:g}s"} for s in self.steps]


class Planner:
    """Builds the `Program` from a world standing in the crouch: hand-tip targets, solved one after the
    other by the whole-body IK, each from the pose before."""

    def __init__(self, world: World, motions: Motions = Motions()):
        self.world = world
        self.mo = motions
        self.wb = WholeBody.for_servo(world, "servo")
        self.program = Program()
        self.last: WholeBodyResult | None = None
        self.level: dict[str, np.ndarray] = {}
        """Hand -> the world's vertical in the hand's frame, kept by the poses that ask for it."""
        self.held: dict[str, np.ndarray] = {}
        """Hand -> the world's vertical in the hand's frame when it took hold (`tilt_deg`)."""
        self._before: dict[str, float] = {}

    # -- where things are -----------------------------------------------------------------------------------
    def geom(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(centre, half sizes) of a geom of the model, where it stands now (m)."""
        m, d = self.world.core.mj.model, self.world.core.mj.data
        g = m.geom(name).id
        return d.geom_xpos[g].copy(), m.geom_size[g].copy()

    def tip(self, hand: str) -> np.ndarray:
        """Where a hand's tip is in the last pose solved (m)."""
        return self._frame(f"{hand}_hand_tip")[0]

    def _frame(self, site: str) -> tuple[np.ndarray, np.ndarray]:
        m = self.world.core.mj.model
        d = mujoco.MjData(m)
        d.qpos[:] = self.last.q_full if self.last is not None else self.world.core.mj.data.qpos
        mujoco.mj_kinematics(m, d)
        s = m.site(site).id
        return d.site_xpos[s].copy(), d.site_xmat[s].reshape(3, 3).copy()

    # -- the program ------------------------------------------------------------------------------------------
    def move(self, name: str, tips: dict[str, np.ndarray], duration_s: float, level: bool = True,
             fresh: bool = False) -> None:
        """Solve a pose that puts the hands' tips (``{"r": xyz, ...}``) where given, and add it. With
        ``level`` a hand that holds something keeps the tilt it took hold with where it can; where it
        cannot, the tips are placed all the same and the tilt left (`tilt_deg`) is noted. ``fresh``:
        solve from the crouch, not from the pose before."""
        r = self._solve(tips, level, fresh) if level and any(h in self.level for h in tips) else None
        if r is None or not r.reached:
            r = self._solve(tips, False, fresh)
        if not r.reached:
            raise RuntimeError(f"kitchen tray program, step {name!r}: {r.message}")
        self.last = r
        pose = {j: round(v, 2) + 0.0 for j, v in r.pose().items()}
        changed = {j: v for j, v in pose.items() if self._before.get(j) != v}
        self._before = pose
        tilt = max((self.tilt_deg(h) for h in tips if h in self.held), default=0.0)
        self.program.steps.append({"name": name, "pose": changed, "duration_s": duration_s, "tilt_deg": tilt})
        self.program.t_s += duration_s

    def _solve(self, tips: dict[str, np.ndarray], level: bool, fresh: bool = False) -> WholeBodyResult:
        targets = []
        for hand, pos in tips.items():
            keep = self.level.get(hand) if level else None
            targets.append(Target(f"{hand}_hand_tip", pos=np.round(pos, 5), axis=keep,
                                  direction=None if keep is None else UP))
        start = None if fresh else self.last
        r = self.wb.solve(targets, start=start)
        if not r.reached and start is not None:  # a local search may stall: again from the crouch
            r = self.wb.solve(targets)
        if not r.reached:  # the posture task may hold a hand a little short: 2 mm will do
            r = self.wb.solve(targets, start=start, tol_m=FAR_M)
        return r

    def tilt_deg(self, hand: str) -> float:
        """How far (degrees) what ``hand`` holds is tilted in the last pose, from how it stood when taken."""
        up = self._frame(f"{hand}_hand_tip")[1] @ self.held[hand]
        return float(np.degrees(np.arccos(np.clip(up @ UP, -1.0, 1.0))))

    def stand(self, name: str, duration_s: float) -> None:
        """Back to the crouch the program started from."""
        pose = {j: float(CROUCH.get(j, 0)) for j in self.wb.joints}
        self.program.steps.append({"name": name, "pose": {j: v for j, v in pose.items() if self._before.get(j) != v},
                                   "duration_s": duration_s})
        self._before = pose
        self.program.t_s += duration_s

    def wait(self, name: str, duration_s: float) -> None:
        self.program.steps.append({"name": name, "pose": {}, "duration_s": duration_s})
        self.program.t_s += duration_s

    def at_now(self, name: str, **event: Any) -> None:
        self.program.events.append({"at": round(self.program.t_s, 3), **event, "name": name})

    def grasp(self, hands: str, obj: str, grip: str, where: np.ndarray, shape: dict[str, Any]) -> None:
        """Take hold of ``obj`` now with ``hands`` (``"r"``, ``"l"`` or ``"rl"``): add the grip body at
        ``where`` (inside ``obj``) and weld each hand to it and it to ``obj`` (two hands share one grip)."""
        who = " and ".join(SIDES[h] for h in hands)
        self.at_now(f"{obj}: the {who} hand{'s' * (len(hands) > 1)} take{'s' * (len(hands) == 1)} it",
                    add_body={kind: {"name": grip, **fields, "color": "red", "pos": [round(float(x), 4) for x in where]}
                              for kind, fields in shape.items()},
                    no_collision=[grip, obj, "pelvis"])
        for h in hands:
            self.at_now(f"{obj}: the {SIDES[h]} hand welded to the grip", make_joint=[HANDS[h], grip])
            self.held[h] = self._frame(f"{h}_hand_tip")[1].T @ UP
            self.level.setdefault(h, self.held[h])
        self.at_now(f"{obj}: the grip welded to it", make_joint=[grip, obj])

    def let_go(self, hands: str, grip: str) -> None:
        """Let go of what ``grip`` holds: remove the grip, and its welds with it."""
        self.at_now(f"the {' and '.join(SIDES[h] for h in hands)} let{'s' * (len(hands) == 1)} go "
                    "(the grip and its welds removed)", remove_body=grip)
        for h in hands:
            self.held.pop(h, None)
            self.level.pop(h, None)

    def turn(self, name: str, deltas: dict[str, float], duration_s: float) -> None:
        """Move some joints by ``deltas`` (degrees) from the pose before, the others held: how both hands
        carry the tray. Equal changes of the two shoulder pitches turn both arms about the one line
        through both shoulders, and the waist turns both about one vertical: either way the two hands
        move as one rigid body, as the welds to the tray hold them (no IK pose of the two hands keeps
        that exactly)."""
        pose = dict(self._before)
        for j, d in deltas.items():
            pose[j] = round(pose[j] + d, 2) + 0.0
        self.program.steps.append({"name": name, "pose": {j: pose[j] for j in deltas}, "duration_s": duration_s,
                                   "tilt_deg": 0.0})
        self._before = pose
        self.program.t_s += duration_s

    def waist(self) -> np.ndarray:
        """Where the waist's axis stands (x, y, m) in the last pose solved."""
        m = self.world.core.mj.model
        d = mujoco.MjData(m)
        d.qpos[:] = self.last.q_full
        mujoco.mj_kinematics(m, d)
        return d.xpos[m.body("torso").id][:2].copy()

    def upright(self, hand: str, tip: np.ndarray) -> np.ndarray:
        """The world's vertical in the hand's frame in a pose (solved from the crouch) with its tip at
        ``tip``: the tilt to take a dish with so that it can be set down level there."""
        r = self.wb.solve([Target(f"{hand}_hand_tip", pos=np.round(tip, 5))])
        m = self.world.core.mj.model
        d = mujoco.MjData(m)
        d.qpos[:] = r.q_full
        mujoco.mj_kinematics(m, d)
        return d.site_xmat[m.site(f"{hand}_hand_tip").id].reshape(3, 3).T @ UP


def _up(point: np.ndarray, dz_m: float) -> np.ndarray:
    """``point`` raised by ``dz_m``."""
    return np.asarray(point, dtype=np.float64) + np.array([0.0, 0.0, dz_m])


def _turned(point: np.ndarray, yaw_deg: float, about: np.ndarray) -> np.ndarray:
    """``point`` turned by ``yaw_deg`` about the vertical through ``about`` (x, y)."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    x, y = point[0] - about[0], point[1] - about[1]
    return np.array([about[0] + c * x - s * y, about[1] + s * x + c * y, point[2]])


def plan(world: World, motions: Motions = Motions()) -> Program:
    """The whole program, from a world built from scenarios/kitchen_tray.yaml standing in the crouch
    (ticked to ``CROUCH_S + SETTLE_S``)."""
    p = Planner(world, motions)
    mo = motions
    tray, tray_half = p.geom("tray")
    stack_top = tray[2] + tray_half[2]
    for name, hand in DISHES:
        dish, half = p.geom(name)
        top = _up(dish, half[1] + mo.gap_m)  # a cylinder's size: radius, half length
        rest = np.array([tray[0], tray[1], stack_top + half[1]])  # where it comes to rest on the stack
        place = _up(rest, half[1] + mo.gap_m + mo.clear_m)
        p.level[hand] = p.upright(hand, place)
        p.move(f"{name}: above it", {hand: _up(top, mo.above_m)}, mo.reach_s)
        p.move(f"{name}: onto it", {hand: top}, mo.down_s)
        p.wait(f"{name}: take it", mo.hold_s)
        p.grasp(hand, name, f"grip_{name}", dish, DISH_GRIP)
        p.move(f"{name}: lift it", {hand: _up(top, mo.above_m)}, mo.lift_s, level=False)
        p.move(f"{name}: over the tray", {hand: _up(place, mo.above_m)}, mo.over_s, level=False)
        p.move(f"{name}: onto the stack", {hand: place}, mo.down_s)
        p.wait(f"{name}: set it down", mo.hold_s)
        p.let_go(hand, f"grip_{name}")
        p.move(f"{name}: hand up", {hand: _up(place, mo.above_m)}, mo.lift_s)
        stack_top += 2 * half[1]
    rims = {h: p.geom(f"tray_rim_{h}") for h in HANDS}
    holds = {h: _up(c, size[2] + mo.gap_m) for h, (c, size) in rims.items()}
    p.move("tray: above its rims", {h: _up(x, mo.above_m / 2) for h, x in holds.items()}, mo.reach_s, fresh=True)
    p.move("tray: onto its rims", holds, mo.down_s)
    p.wait("tray: take it", mo.hold_s)
    p.grasp("rl", "tray", "grip_tray", tray, TRAY_GRIP)
    shoulders = ("l_shoulder_pitch", "r_shoulder_pitch")
    p.turn("tray: lift it", {j: -mo.lift_deg for j in shoulders}, mo.lift_s * 2)
    p.turn("tray: carry it", {"waist_yaw": mo.turn_deg}, mo.carry_s)
    p.turn("tray: set it down", {j: mo.lift_deg for j in shoulders}, mo.lift_s * 2)
    p.wait("tray: let it rest", mo.hold_s)
    p.let_go("rl", "grip_tray")
    axis = p.waist()
    p.move("hands up", {h: _up(_turned(x, mo.turn_deg, axis), mo.above_m) for h, x in holds.items()}, mo.lift_s)
    p.stand("stand", mo.back_s)
    return p.program


def standing(world: World) -> World:
    """Tick a world built from the scenario through the crouch, to where the program starts."""
    world.tick(round((CROUCH_S + SETTLE_S) / (world.dt_ns * 1e-9)) - world.tick_count)
    return world


SEQUENCE_MARK, EVENTS_MARK = "# <generated sequence>", "# <generated events>"
"""The lines of scenarios/kitchen_tray.yaml between a mark and its end (``# </generated ...>``) are the
program `to_yaml` writes."""


def _flow(value: Any) -> str:
    return yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=10**6).strip()


def to_yaml(program: Program) -> dict[str, str]:
    """The program as scenarios/kitchen_tray.yaml writes it: mark -> its lines (the servo's sequence, one
    step a line with the joints that change, the step's name as a comment; the events, one a line)."""
    names = ["crouch", "stand still"] + [s["name"] for s in program.steps]
    seq = [f"        - {_flow(step)}   # {name}" for step, name in zip(program.sequence(), names, strict=True)]
    events = []
    for e in program.events:
        event = {"at": f"{e['at']:g}s", **{k: v for k, v in e.items() if k not in ("at", "name")}}
        events.append(f"  - {_flow(event)}   # {e['name']}")
    return {SEQUENCE_MARK: "\n".join(seq), EVENTS_MARK: "\n".join(events)}


def write(program: Program, path: Path = SCENARIO) -> None:
    """Replace the generated parts of the scenario file with ``program``."""
    text = path.read_text()
    for mark, lines in to_yaml(program).items():
        end = mark.replace("<", "</")
        block = re.compile(rf"^([ \t]*{re.escape(mark)}[^\n]*\n).*?^([ \t]*{re.escape(end)})", re.M | re.S)
        if not block.search(text):
            raise SystemExit(f"{path}: no {mark!r} ... {end!r} block to write the program into")
        text = block.sub(lambda m, lines=lines: m.group(1) + lines + "\n" + m.group(2), text, count=1)
    path.write_text(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--yaml", action="store_true", help="print the program (servo sequence and events)")
    parser.add_argument("--write", action="store_true", help="write the program into scenarios/kitchen_tray.yaml")
    args = parser.parse_args()
    world = standing(load_scenario(SCENARIO).build())
    try:
        program = plan(world)
    finally:
        world.close()
    if args.yaml:
        for mark, lines in to_yaml(program).items():
            print(mark, lines, sep="\n")
        return
    if args.write:
        write(program)
        print(f"wrote the program ({len(program.steps)} steps, {len(program.events)} events, "
              f"{program.t_s:g} s) into {SCENARIO.name}")
        return
    print(f"the program: {len(program.steps)} steps, {len(program.events)} events, {program.t_s:g} s; "
          "the dishes set down tilted at most "
          f"{max(s.get('tilt_deg', 0.0) for s in program.steps if 'onto the stack' in s['name']):.1f} degrees")
    run(program)


def run(program: Program) -> None:
    """Run the scenario (which holds the program when it is the one written) and print its checks."""
    shipped = load_scenario(SCENARIO)
    if to_yaml(program)[SEQUENCE_MARK] not in SCENARIO.read_text():
        print(f"(the program differs from the one in {SCENARIO.name}: --write it there to run it)")
    result = run_scenario(shipped)
    for e in result.expectations:
        print(f"  {'ok  ' if e.passed else 'FAIL'} {e.label}" + (f": {e.detail}" if e.detail else ""))
    error = f"; {result.error}" if result.error else ""
    print(f"{result.sim_time:g} s simulated in {result.wall_time:.1f} s{error}")


if __name__ == "__main__":
    main()
