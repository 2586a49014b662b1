"""Breakout: a non-physical rule module and the player that moves the paddle (the paper's block game).

`BreakoutRules` is the micro-kernel point of the paper: a function the physics cannot express, added
as a module. A block the ball touches disappears once the ball has bounced off it (its geoms stop
colliding and become invisible); the game is won when every block is gone. Which blocks are gone is
the module's state, so a rollback brings blocks back exactly as they were.

How a block disappears: the MuJoCo core has no run-time switch for an object's collisions, so the
rules switch the block's geoms off in the core's current model (``contype``, ``conaffinity`` and
the alpha of ``rgba``) through `MujocoLink`, re-applying their own state after every restore and
whenever the core switches to another compiled structure. Removing the rules module leaves the
blocks as they are.

`Paddle` plays: it serves the ball once, then moves the paddle (a slide joint) under the ball and
aims: the paddle is round, so where it meets the ball sets the direction the ball leaves in; it
picks the point that sends the ball towards the block the rules name in ``aim``.
"""

from __future__ import annotations

import fnmatch
import math

import numpy as np

from dynabrain.orchestrator.kernel.module import Module, Param, Port, SetupContext

from .mujoco.access import MujocoLink, fail


class BreakoutRules(Module):
    """Blocks the ball has bounced off disappear; the game is won when all are gone.

    Targets: the blocks (body names or glob patterns, ``block_*``). Outputs: ``alive`` (n,) 1 or 0
    per block, ``remaining``, ``hits`` (blocks removed so far), ``won`` (1 once none remains),
    ``aim`` (2, m): the x, y of the block to play at next (the lowest remaining one).
    """

    PARAMS = (Param("ball", "ball", doc="the ball's body"),)

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._blocks: list[str] = [t for t in self.targets if not any(c in t for c in "*?[")]

    @property
    def blocks(self) -> list[str]:
        return list(self._blocks)

    def outputs(self) -> list[Port]:
        n = len(self._blocks)
        return [Port("alive", (n,), "1"), Port("remaining", (), "1"), Port("hits", (), "1"), Port("won", (), "1"),
                Port("aim", (2,), "m", "x, y of the block to play at")]

    def setup(self, ctx: SetupContext) -> None:
        self._link = MujocoLink(self.name, ctx.core)
        bodies = ctx.core.bodies()
        blocks: list[str] = []
        for pattern in self.targets or ["block_*"]:
            hits = fnmatch.filter(bodies, pattern)
            if not hits:
                raise fail(self.name, "targets", f"{pattern!r} matches no body of the scene")
            blocks += [b for b in hits if b not in blocks]
        if self.params["ball"] in blocks or self.params["ball"] not in bodies:
            raise fail(self.name, "params.ball", f"{self.params['ball']!r} is not a body of the scene, apart "
                       "from the blocks")
        self._blocks = blocks
        self._alive = np.ones(len(blocks), dtype=bool)
        self._touched = np.zeros(len(blocks), dtype=bool)
        self._hits = 0
        self._link.changed()
        self._resolve()

    def _resolve(self) -> None:
        """Geom ids in the current model, their collision bits and colours as the model has them."""
        link, m = self._link, self._link.model
        self._ball_geoms = link.subtree_geoms(self.params["ball"], field="params.ball")
        if not self._ball_geoms:
            raise fail(self.name, "params.ball", f"the ball {self.params['ball']!r} has no geom that can collide")
        self._geom_block = np.full(m.ngeom, -1, dtype=np.intp)
        self._geoms: list[list[int]] = []
        for k, block in enumerate(self._blocks):
            geoms = link.subtree_geoms(block, colliding=False)
            self._geoms.append(geoms)
            self._geom_block[geoms] = k
        self._is_ball = np.zeros(m.ngeom, dtype=bool)
        self._is_ball[self._ball_geoms] = True
        every = [g for gs in self._geoms for g in gs]
        self._bits = {g: (int(m.geom_contype[g]), int(m.geom_conaffinity[g]), float(m.geom_rgba[g, 3])) for g in every}
        self._shown = np.ones(len(self._blocks), dtype=bool)  # what the model shows now
        self._centres = np.array([link.data.xpos[link.lookup("body", b)][:2] for b in self._blocks])
        self._apply()

    def _apply(self) -> None:
        """Make the model show exactly the alive blocks."""
        m = self._link.model
        for k in np.flatnonzero(self._shown != self._alive):
            for g in self._geoms[k]:
                ct, ca, alpha = self._bits[g] if self._alive[k] else (0, 0, 0.0)
                m.geom_contype[g], m.geom_conaffinity[g], m.geom_rgba[g, 3] = ct, ca, alpha
        self._shown = self._alive.copy()

    def start(self, t_ns: int) -> None:
        self._write()

    def step(self, t_ns: int, dt_ns: int) -> None:
        if self._link.changed():
            self._resolve()
        d = self._link.data
        touching = np.zeros(len(self._blocks), dtype=bool)
        if d.ncon:
            g = d.contact.geom
            with_ball = self._is_ball[g[:, 0]] | self._is_ball[g[:, 1]]
            blocks = np.maximum(self._geom_block[g[:, 0]], self._geom_block[g[:, 1]])[with_ball]
            touching[blocks[blocks >= 0]] = True
        touching &= self._alive
        gone = self._touched & ~touching  # bounced off: the contact is over
        if gone.any():
            self._alive = self._alive & ~gone
            self._hits += int(gone.sum())
            self._apply()
        self._touched = touching
        self._write()

    def _write(self) -> None:
        out = self.out
        out["alive"][...] = self._alive
        out["remaining"][...] = int(self._alive.sum())
        out["hits"][...] = self._hits
        out["won"][...] = 1.0 if not self._alive.any() else 0.0
        if self._alive.any():
            idx = np.flatnonzero(self._alive)
            lowest = np.argmin(self._centres[idx, 1] + 1e-3 * np.abs(self._centres[idx, 0]))
            out["aim"][...] = self._centres[idx[lowest]]

    def get_state(self) -> tuple:
        return (self._alive.copy(), self._touched.copy(), self._hits)

    def set_state(self, state: tuple) -> None:
        alive, touched, self._hits = state
        self._alive, self._touched = alive.copy(), touched.copy()
        if self._link.changed():
            self._resolve()
        else:
            self._apply()


class Paddle(Module):
    """Serves, then keeps the round paddle under the ball and aims it at the next block.

    Inputs: ``ball_pos`` (3, m), ``ball_vel`` (3, m/s) (the core's ``ball.pos``, ``ball.linvel``),
    ``paddle_q`` (m), ``paddle_qd`` (m/s) (the paddle's slide joint), ``aim`` (2, m) (the rules').
    Outputs: ``paddle_force`` (N) for the paddle's joint; ``serve_x``, ``serve_y`` (N) for the ball's
    two slide joints: one step of force that gives the ball the ``serve`` velocity.
    """

    PARAMS = (
        Param("line", -0.5, unit="m", dimension="length", doc="y of the paddle's axis"),
        Param("reach", 0.105, unit="m", dimension="length", doc="paddle radius plus ball radius"),
        Param("walls", (-0.475, 0.475), unit="m", doc="x limits of the ball's centre (side walls)"),
        Param("travel", (-0.42, 0.42), unit="m", doc="x limits of the paddle"),
        Param("mass", 0.5, unit="kg", dimension="mass", doc="paddle mass"),
        Param("omega", 40.0, unit="rad/s", doc="natural frequency of the paddle's position loop"),
        Param("serve", (0.35, 0.9), unit="m/s", doc="the ball's velocity after the serve"),
        Param("ball_mass", 0.05, unit="kg", dimension="mass", doc="ball mass (for the serve)"),
        Param("min_angle", 0.5, unit="rad", dimension="angle", doc="least angle of a return above the horizontal"),
    )

    def inputs(self) -> list[Port]:
        return [Port("ball_pos", (3,), "m"), Port("ball_vel", (3,), "m/s"), Port("paddle_q", (), "m"),
                Port("paddle_qd", (), "m/s"), Port("aim", (2,), "m")]

    def outputs(self) -> list[Port]:
        return [Port("paddle_force", (), "N"), Port("serve_x", (), "N"), Port("serve_y", (), "N"),
                Port("target", (), "m", "where the paddle is going")]

    def start(self, t_ns: int) -> None:
        self._served = False
        for port in ("paddle_force", "serve_x", "serve_y", "target"):
            self.out[port][...] = 0.0

    def step(self, t_ns: int, dt_ns: int) -> None:
        p, inp, out = self.params, self.inp, self.out
        ball, vel = inp["ball_pos"], inp["ball_vel"]
        if not self._served:
            impulse = p["ball_mass"] / (dt_ns * 1e-9)
            out["serve_x"][...] = impulse * (p["serve"][0] - float(vel[0]))
            out["serve_y"][...] = impulse * (p["serve"][1] - float(vel[1]))
            self._served = True
        else:
            out["serve_x"][...] = 0.0
            out["serve_y"][...] = 0.0
        target = self._target(float(ball[0]), float(ball[1]), float(vel[0]), float(vel[1]), inp["aim"])
        lo, hi = p["travel"]
        target = min(max(target, lo), hi)
        w = p["omega"]
        out["target"][...] = target
        error, rate = target - float(inp["paddle_q"]), float(inp["paddle_qd"])
        out["paddle_force"][...] = p["mass"] * (w * w * error - 2 * w * rate)

    def _target(self, x: float, y: float, vx: float, vy: float, aim: np.ndarray) -> float:
        """Paddle x that returns the ball towards ``aim``; under the ball while it flies away."""
        p = self.params
        if vy >= -1e-3:
            return x
        speed = math.hypot(vx, vy)
        ux, uy = vx / speed, vy / speed
        ny = 1.0
        for _ in range(3):  # the hit point depends on the normal, the normal on the hit point
            y_hit = p["line"] + p["reach"] * ny
            x_hit = _fold(x + vx * (y_hit - y) / vy, *p["walls"])
            dx, dy = float(aim[0]) - x_hit, max(float(aim[1]) - y_hit, 1e-3)
            angle = max(math.atan2(dy, dx), p["min_angle"])
            angle = min(angle, math.pi - p["min_angle"])
            out_x, out_y = math.cos(angle), math.sin(angle)
            nx, ny = out_x - _ux_at(ux, x, vx, y_hit, y, vy, p["walls"]), out_y - uy
            norm = math.hypot(nx, ny)
            nx, ny = nx / norm, ny / norm
        return x_hit - p["reach"] * nx

    def get_state(self) -> bool:
        return self._served

    def set_state(self, state: bool) -> None:
        self._served = state


def _fold(x: float, lo: float, hi: float) -> float:
    """Where a point moving freely along x ends up between two walls that reflect it."""
    span = hi - lo
    s = (x - lo) % (2 * span)
    return lo + (s if s <= span else 2 * span - s)


def _ux_at(ux: float, x: float, vx: float, y_hit: float, y: float, vy: float, walls: tuple[float, float]) -> float:
    """The x direction of the ball when it reaches ``y_hit``: reversed by each wall it bounces off."""
    lo, hi = walls
    free = x + vx * (y_hit - y) / vy
    bounces = math.floor((free - lo) / (hi - lo))
    return ux if bounces % 2 == 0 else -ux
