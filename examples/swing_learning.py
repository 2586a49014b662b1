"""Learn to pump the swing (EusDyna Fig. 19) with CMA-ES, inside the embedded simulator.

The world is `scenarios/swing_learning.yaml`: the humanoid on the swing, its legs driven by
`dynabrain.modules.policies:SwingPolicy` (offsets = amplitude * tanh(w_angle * angle + w_rate * rate
+ bias), the same amplitudes and speed limit as the hand-written rule of `scenarios/swing.yaml`).
CMA-ES (the ``cma`` package) searches the three weights; each generation's candidates are the
branches of one `Batch` run, each branch the whole episode from t = 0 with its own parameter
overrides (``params={"policy.w_angle": [...], ...}``). Fitness: the swing's amplitude after the
horizon (the ``swings`` meter's ``amplitude``: half the peak-to-peak of the last swing), measured the
same way for the hand rule.

    .venv/bin/python examples/swing_learning.py [--generations 20] [--backend processes] [--out runs/swing_policy.json]

Prints each generation, then the hand rule's and the learned policy's amplitude, and writes the learned
parameters (JSON) for the ``policy`` module's ``params`` in `scenarios/swing_learning.yaml`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cma
import numpy as np

from dynabrain.orchestrator import Batch, World, load_world

ROOT = Path(__file__).resolve().parents[1]
LEARNING = ROOT / "scenarios" / "swing_learning.yaml"
HAND_RULE = ROOT / "scenarios" / "swing.yaml"
PARAMS = ("w_angle", "w_rate", "bias")
SCALE = np.array([10.0, 10.0, 1.0])
"""The optimiser's unit for each parameter: it searches x with weight = SCALE * x, x in [-10, 10]."""
AMPLITUDE = "swings.amplitude"


def amplitudes(batch: Batch, ticks: int, weights: np.ndarray) -> np.ndarray:
    """The swing's amplitude after ``ticks`` ticks for each row of ``weights`` (w_angle, w_rate, bias),
    one branch per row from the batch world's state; 0 for a branch that failed or never swung."""
    weights = np.atleast_2d(weights)
    result = batch.run(ticks, branches=len(weights), keep_states=False, record=[AMPLITUDE],
                       params={f"policy.{name}": weights[:, k].tolist() for k, name in enumerate(PARAMS)})
    reached = result.signals[AMPLITUDE][:, -1]
    return np.where(np.isfinite(reached), reached, 0.0)


def hand_rule_amplitude(ticks: int) -> float:
    """The amplitude the hand rule (`scenarios/swing.yaml`, PhasePump) reaches after ``ticks`` ticks."""
    with load_world(HAND_RULE) as world:
        return float(world.run(ticks, record=[AMPLITUDE])[AMPLITUDE][-1])


@dataclass
class Training:
    """What `train` found: the best weights, their amplitude, and per generation the best amplitude."""

    weights: dict[str, float]
    amplitude: float
    generations: list[float] = field(default_factory=list)
    episodes: int = 0
    wall_s: float = 0.0


def train(world: World, *, generations: int, ticks: int, popsize: int = 8, seed: int = 1, sigma0: float = 1.0,
          backend: str = "serial", log: Callable[[str], None] = print) -> Training:
    """CMA-ES over the policy's weights, starting from no pumping (all zero); ``seed`` (>= 1) fixes the
    optimiser's samples, so a run is repeatable. Every candidate runs ``ticks`` ticks from ``world``'s state."""
    options = {"popsize": popsize, "seed": seed, "bounds": [-10, 10], "verbose": -9}
    es = cma.CMAEvolutionStrategy(np.zeros(len(PARAMS)), sigma0, options)
    best = Training(dict.fromkeys(PARAMS, 0.0), -math.inf)
    t0 = time.perf_counter()
    with Batch(world, backend=backend) as batch:
        for g in range(generations):
            xs = es.ask()
            reached = amplitudes(batch, ticks, np.asarray(xs) * SCALE)
            es.tell(xs, (-reached).tolist())  # cma minimises
            k = int(np.argmax(reached))
            if reached[k] > best.amplitude:
                best.amplitude = float(reached[k])
                best.weights = {name: float(v) for name, v in zip(PARAMS, np.asarray(xs[k]) * SCALE, strict=True)}
            best.generations.append(float(reached[k]))
            best.episodes += len(xs)
            wall = time.perf_counter() - t0
            log(f"generation {g + 1:3d}: best {reached[k]:.4f} rad, mean {reached.mean():.4f} rad, best so far "
                f"{best.amplitude:.4f} rad  ({best.episodes / wall:.1f} episodes/s)")
    best.wall_s = time.perf_counter() - t0
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generations", type=int, default=20)
    ap.add_argument("--popsize", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1, help="the optimiser's seed (>= 1)")
    ap.add_argument("--horizon", type=float, default=16.0, help="seconds of swinging per episode")
    ap.add_argument("--backend", default="processes", choices=["serial", "processes", "ray", "auto"])
    ap.add_argument("--out", type=Path, default=Path("runs/swing_policy.json"))
    args = ap.parse_args(argv)
    if args.seed < 1:
        ap.error("--seed must be >= 1 (cma draws a random seed for 0)")
    with load_world(LEARNING) as world:
        ticks = round(args.horizon / (world.dt_ns * 1e-9))
        print(f"CMA-ES on {', '.join(PARAMS)}: {args.generations} generations of {args.popsize}, "
              f"{args.horizon:g} s episodes ({ticks} ticks), backend {args.backend}")
        found = train(world, generations=args.generations, ticks=ticks, popsize=args.popsize, seed=args.seed,
                      backend=args.backend)
    hand = hand_rule_amplitude(ticks)
    print(f"\n{found.episodes} episodes in {found.wall_s:.1f} s ({found.episodes / found.wall_s:.1f} episodes/s)")
    print(f"hand rule (PhasePump):  amplitude {hand:.4f} rad after {args.horizon:g} s")
    print(f"learned (SwingPolicy):  amplitude {found.amplitude:.4f} rad after {args.horizon:g} s  "
          f"({found.amplitude / hand:.2f}x)")
    print("learned parameters: " + ", ".join(f"{k}: {v:.4g}" for k, v in found.weights.items()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"params": found.weights, "amplitude_rad": found.amplitude,
                                    "hand_rule_amplitude_rad": hand, "horizon_s": args.horizon,
                                    "generations": args.generations, "popsize": args.popsize, "seed": args.seed},
                                   indent=2) + "\n")
    print(f"written to {args.out}")
    return 0 if found.amplitude > hand else 1


if __name__ == "__main__":
    sys.exit(main())
