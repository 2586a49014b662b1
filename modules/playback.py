"""A plan played back on the bus: the values a brain chose for the ticks to come, one row a step.

A receding-horizon controller (`orchestrator.brain.mpc`) writes the plan it chose into this module's
run-time parameters; the module's outputs, connected to the controlled input ports (one output may
drive several ports: both hips from one ``hip`` channel), carry row ``(t - start) / dt`` of the plan at
each step, the first row before the plan starts and the last after it ends. So the world keeps ticking
on the last plan while the brain thinks about the next one, and a new plan takes over at a tick the
brain chooses, in simulation as on a world served over the bridge. The plan is a parameter: setting it is
an edit the world's history and log keep, so a rollback to a tick under that plan plays the same
values again, and a replay of the log sets it at the same tick.

Parameters: ``channels`` (``"hip,knee"``: one output port a name; ``"arm:3"`` for a vector of 3),
``plan`` (run-time: an array of rows, each the channels' values laid end to end), ``start`` (run-time:
the time of row 0, s), ``hold`` (the values before any plan is given; default zeros), ``units`` (each
channel's unit, comma-separated: those of the ports it drives).
"""

from __future__ import annotations

import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.module import Capabilities, Module, Param, Port


def parse_channels(spec: str, where: str = "channels") -> list[tuple[str, int]]:
    """``"hip,knee,arm:3"`` -> [("hip", 1), ("knee", 1), ("arm", 3)]."""
    out: list[tuple[str, int]] = []
    for part in (p.strip() for p in str(spec).split(",")):
        name, _, size = part.partition(":")
        if not name.isidentifier():
            raise DynabrainError(f"PlanPlayer [{where}]: {part!r} is not a channel (a name, or name:size)")
        if size and (not size.isdigit() or int(size) < 1):
            raise DynabrainError(f"PlanPlayer [{where}]: the size of {name!r} is {size!r}; a positive integer")
        if any(n == name for n, _ in out):
            raise DynabrainError(f"PlanPlayer [{where}]: channel {name!r} is named twice")
        out.append((name, int(size) if size else 1))
    return out


class PlanPlayer(Module):
    """Plays a plan (rows of the channels' values, one a step) onto its output ports (module docstring)."""

    PARAMS = (
        Param("channels", "u", doc="output ports: 'name' or 'name:size', comma-separated"),
        Param("plan", np.zeros((0, 0)), runtime=True, doc="rows of values, one a step, channels end to end"),
        Param("start", 0.0, unit="s", runtime=True, dimension="time", doc="time of the plan's first row"),
        Param("hold", np.zeros((0,)), doc="values before a plan is given (default zeros)"),
        Param("units", "", doc="each channel's unit, comma-separated (default '1'): those of the ports it drives"),
    )
    CAPABILITIES = Capabilities(feedthrough=False)

    def __init__(self, name: str, **params):
        super().__init__(name, **params)
        self._channels = parse_channels(self.params["channels"])
        self.width = sum(size for _, size in self._channels)
        hold = np.asarray(self.params["hold"], dtype=np.float64).reshape(-1)
        if hold.size not in (0, self.width):
            raise DynabrainError(f"module {name!r} [params.hold]: {hold.size} values for channels of {self.width}")
        self._hold = hold if hold.size else np.zeros(self.width)
        self._check_plan(self.params["plan"])

    def _check_plan(self, plan: np.ndarray) -> None:
        arr = np.asarray(plan)
        if arr.size and (arr.ndim != 2 or arr.shape[1] != self.width):
            raise DynabrainError(f"module {self.name!r} [params.plan]: rows of {self.width} values "
                                 f"({self.params['channels']}), got shape {arr.shape}")

    def set_param(self, name, value, *, running=True):
        if name == "plan":  # checked before it is taken: a refused plan leaves the last one playing
            try:
                arr = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                raise DynabrainError(f"module {self.name!r} [params.plan]: expected rows of numbers") from None
            self._check_plan(arr)
        super().set_param(name, value, running=running)

    def outputs(self):
        units = [u.strip() or "1" for u in self.params["units"].split(",")] if self.params["units"] else []
        units += ["1"] * (len(self._channels) - len(units))
        return tuple(Port(name, () if size == 1 else (size,), unit)
                     for (name, size), unit in zip(self._channels, units, strict=False))

    def start(self, t_ns):
        self._write(self._hold)

    def step(self, t_ns, dt_ns):
        plan = self.params["plan"]
        if not len(plan):
            self._write(self._hold)
            return
        row = (t_ns - round(self.params["start"] * 1e9)) // dt_ns
        self._write(plan[min(max(int(row), 0), len(plan) - 1)])

    def _write(self, values: np.ndarray) -> None:
        self.out_flat[:] = values
