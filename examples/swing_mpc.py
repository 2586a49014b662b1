"""The swing pumped by receding-horizon control on imagined futures, against the hand rule and CMA-ES.

The world: `scenarios/swing_mpc.yaml`, the humanoid on the swing with its hips and knees left to the
brain. Every ``--every`` of simulated time the brain imagines ``--samples`` futures of the next
``--horizon`` from the latest state (MPPI over spline knots of the hip and knee offsets, the hand
rule's ranges), scores each by the swing's amplitude at the end (its meter's: half the last swing's
peak-to-peak), and plays the weighted best until the next replan
(`orchestrator/brain/mpc.py`). In one run, with the same meter (``swings.amplitude``: half the last
swing's peak-to-peak) after the same time from t = 0, it compares

- the hand rule (`scenarios/swing.yaml`: legs follow the sign of the swing's rate),
- the policy CMA-ES learned offline (`scenarios/swing_learning.yaml`),
- MPC, thinking while it acts.

    .venv/bin/python examples/swing_mpc.py [--duration 16] [--samples 32] [--horizon 2.0] [--backend processes]
    .venv/bin/python examples/swing_mpc.py --log runs/swing_mpc.mcap    # each replan's chosen future in Foxglove
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.brain.mpc import Control, Futures, Mpc

ROOT = Path(__file__).resolve().parents[1]
MPC_SWING = ROOT / "scenarios" / "swing_mpc.yaml"
HAND_RULE = ROOT / "scenarios" / "swing.yaml"
LEARNED = ROOT / "scenarios" / "swing_learning.yaml"
PIVOT = ["core.swing_pivot.q", "core.swing_pivot.qd", "swings.amplitude"]
W2 = 9.81 / 0.85
"""The swing's natural frequency squared (1/s^2): the robot sits about 0.85 m under the pivot."""
HIP, KNEE = math.radians(70), math.radians(90)
"""The hand rule's amplitudes: the brain may move the legs as far (reaching forward and tucking in)."""


def legs() -> dict[str, Control]:
    """Both hips from one channel, both knees from another, from the sitting pose to the hand rule's
    reach (the offsets it gives while the swing moves forward)."""
    return {"hip": Control(["servo.l_hip_pitch.q_ref", "servo.r_hip_pitch.q_ref"], -HIP, 0.0),
            "knee": Control(["servo.l_knee.q_ref", "servo.r_knee.q_ref"], -KNEE, 0.0)}


def amplitude_cost(f: Futures) -> np.ndarray:
    """Minus the swing's amplitude as its meter has it at the end of the horizon (half the peak-to-peak
    of the last swing: the same measure as the comparison)."""
    return -f["swings.amplitude"][:, -1]


def radius_cost(f: Futures) -> np.ndarray:
    """Minus the swing's squared amplitude at the end of the horizon (the phase-plane radius: fooled by
    the legs moving the robot's weight, which moves the hinge without pumping)."""
    q, qd = f["core.swing_pivot.q"][:, -1], f["core.swing_pivot.qd"][:, -1]
    return -(q ** 2 + qd ** 2 / W2)


def amplitude(path: Path, seconds: float) -> float:
    """The swing's amplitude after ``seconds`` of a scenario that pumps by itself."""
    with load_world(path) as world:
        world.tick(round(seconds / (world.dt_ns * 1e-9)))
        return float(world.get("swings.amplitude"))


def pump_by_mpc(seconds: float, samples: int, horizon: float, every: float, backend: str,
                log: Path | None, knots: int = 5) -> tuple[float, str]:
    with load_world(MPC_SWING) as world:
        logger = None
        if log is not None:
            from dynabrain.orchestrator.logs.logger import McapLogger

            log.parent.mkdir(parents=True, exist_ok=True)
            logger = McapLogger(log).attach(world)
        with Mpc(world, legs(), amplitude_cost, record=PIVOT, horizon=horizon, knots=knots, samples=samples,
                 method="mppi", backend=backend, name="pump") as mpc:
            stats = mpc.run(world, seconds, every=every)
        if logger is not None:
            logger.close()
        return float(world.get("swings.amplitude")), stats.summary()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=16.0, help="seconds of swinging")
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--horizon", type=float, default=2.0, help="seconds")
    ap.add_argument("--knots", type=int, default=5, help="spline knots a control over the horizon")
    ap.add_argument("--every", type=float, default=0.1, help="seconds between replans")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--log", type=Path, help="record the MPC run and its imagined futures (MCAP)")
    opts = ap.parse_args()
    hand = amplitude(HAND_RULE, opts.duration)
    learned = amplitude(LEARNED, opts.duration)
    t0 = time.perf_counter()
    mpc, summary = pump_by_mpc(opts.duration, opts.samples, opts.horizon, opts.every, opts.backend, opts.log,
                                opts.knots)
    wall = time.perf_counter() - t0
    print(f"swing amplitude after {opts.duration:g} s:")
    print(f"  hand rule (legs follow the rate's sign)  {hand:.4f} rad")
    print(f"  CMA-ES policy (learned offline)          {learned:.4f} rad")
    print(f"  MPC ({opts.samples} futures of {opts.horizon:g} s every {opts.every:g} s)  {mpc:.4f} rad  "
          f"({mpc / hand:.2f}x the hand rule)")
    print(f"  MPC: {summary}; {wall:.0f} s of wall time for {opts.duration:g} s simulated")


if __name__ == "__main__":
    main()
