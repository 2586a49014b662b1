"""The parts of one world, made together over one `Context` (`World.parts`)."""

from __future__ import annotations

from dataclasses import dataclass

from .context import Context
from .drive import Drive
from .names import Names
from .realtime import RealtimeRunner
from .scene import SceneEdits
from .stepper import Stepper
from .timeline import Timeline
from .transfer import StateTransfer
from .wiring import Wiring


@dataclass(frozen=True)
class Parts:
    """What `World` delegates to; benches and kernel tools may read them (nothing else should)."""

    context: Context
    timeline: Timeline
    stepper: Stepper
    wiring: Wiring
    scene: SceneEdits
    names: Names
    drive: Drive
    transfer: StateTransfer
    realtime: RealtimeRunner

    @classmethod
    def of(cls, ctx: Context) -> Parts:
        timeline = Timeline(ctx)
        stepper = Stepper(ctx, timeline)
        wiring = Wiring(ctx)
        scene = SceneEdits(ctx, wiring)
        names = Names(ctx, timeline, scene)
        return cls(ctx, timeline, stepper, wiring, scene, names, Drive(ctx, stepper, timeline, names),
                   StateTransfer(ctx, timeline, wiring), RealtimeRunner(ctx, stepper))
