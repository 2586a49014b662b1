"""Names: what ``get`` and ``set`` reach by name. A signal (``module.port``; a core port may leave out
the core's name), a parameter (``module.param``), a body's material (``core.<body>.friction``) or a
body's field as a scenario's expressions read it (``<body>.x``, ``.speed``...). An unknown name raises
naming the closest one."""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import edits
from ..errors import DynabrainError, WiringError
from ..module import Module
from ..structure import Slot
from ..suggest import did_you_mean
from .context import Context
from .scene import SceneEdits
from .timeline import Timeline
from .util import BODY_FIELDS


class Names:
    """Values by name in one world (see the module docstring). The caller holds the world lock."""

    def __init__(self, ctx: Context, timeline: Timeline, scene: SceneEdits):
        self.ctx = ctx
        self.timeline = timeline
        self.scene = scene

    def get(self, name: str) -> Any:
        ctx = self.ctx
        slot = self.resolve_signal(name)
        if slot is not None:
            value = ctx.buf[slot.start:slot.start + slot.size]
            return float(value[0]) if slot.shape == () else value.reshape(slot.shape).copy()
        if self.resolve_param(name) is None:
            material = self.scene.material_target(name)
            if material is not None:
                return getattr(ctx.core.material(material[0]), material[1])  # type: ignore[union-attr]
            field = self.body_field(name)
            if field is not None:
                return field
        module, key = self.split_param(name)
        return module.params[key]

    def body_field(self, name: str) -> Any:
        """``<body>.x`` (``.y``, ``.z``, ``.speed``, ``.vel``, ``.angvel``; the core's name may lead) of a
        body of the core, or None when ``name`` is no such field."""
        core = self.ctx.core
        if core is None:
            return None
        rest = name[len(core.name) + 1:] if name.startswith(f"{core.name}.") else name
        body, _, key = rest.rpartition(".")
        if key not in BODY_FIELDS or body not in core.bodies():
            return None
        if key in ("x", "y", "z"):
            return float(core.body_pose(body)[0]["xyz".index(key)])
        linear, angular = core.body_velocity(body)
        return {"vel": linear, "angvel": angular, "speed": float(np.linalg.norm(linear))}[key]

    def set(self, name: str, value: Any) -> None:
        ctx = self.ctx
        if self.resolve_signal(name) is None and self.resolve_param(name) is None:
            material = self.scene.material_target(name)
            if material is not None:
                self.scene.set_material(material[0], **{material[1]: value})
                return
        target = self.settable(name)
        if isinstance(target, str):
            slot = ctx.structure.layout.slots[target]
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != slot.shape:
                raise WiringError(f"{target} has shape {slot.shape}, got a value of shape {arr.shape}")
            values = arr.reshape(-1)
            ctx.buf[slot.start:slot.start + slot.size] = values
            self.timeline.keep_inputs([(slot.start, values.tobytes())])
            ctx.tell(edits.Set(target, arr.tolist()))
            return
        module, key = target
        module.set_param(key, value, running=ctx.tick > 0)  # its binding tells `Context.param_changed`
        new = module.params[key]
        ctx.edited(edits.SetParam(f"{module.name}.{key}", new.tolist() if hasattr(new, "tolist") else new))

    def settable(self, name: str) -> str | tuple[Module, str]:
        """An input signal's full name, or (module, parameter); raises naming the closest settable name."""
        slot = self.resolve_signal(name)
        if slot is not None:
            full = self.full_signal_name(name)
            if slot.direction != "in":
                raise WiringError(f"{full} is an output of its module; only inputs and parameters can be set")
            conn = self.ctx.structure.driver_of(full)
            if conn is not None:
                raise WiringError(f"{full} is driven by {conn.src}; disconnect it before setting it")
            return full
        return self.split_param(name, settable=True)

    # -- resolving ------------------------------------------------------------------------------------
    def full_signal_name(self, name: str) -> str:
        slots, core = self.ctx.structure.layout.slots, self.ctx.core
        if name in slots or core is None:
            return name
        return f"{core.name}.{name}"

    def resolve_signal(self, name: str) -> Slot | None:
        slots, core = self.ctx.structure.layout.slots, self.ctx.core
        return slots.get(name) or (slots.get(f"{core.name}.{name}") if core is not None else None)

    def resolve_param(self, name: str) -> tuple[Module, str] | None:
        module_name, sep, key = name.partition(".")
        rec = self.ctx.structure.record(module_name) if sep else None
        return (rec.module, key) if rec is not None and key in rec.module.param_specs() else None

    def split_param(self, name: str, settable: bool = False) -> tuple[Module, str]:
        structure = self.ctx.structure
        found = self.resolve_param(name)
        if found is None:
            layout = structure.layout.slots
            signals = [n for n in layout if not settable or layout[n].direction == "in"]
            candidates = [f"{r.name}.{p}" for r in structure.records for p in r.module.param_specs()] + signals
            raise DynabrainError(f"no signal or parameter named {name!r}" + did_you_mean(name, candidates))
        return found

    def signal_slot(self, name: str, what: str) -> Slot:
        slot = self.resolve_signal(name)
        if slot is None:
            raise WiringError(f"{what}: no signal {name!r}"
                              + did_you_mean(name, list(self.ctx.structure.layout.slots)))
        return slot

    def input_slot(self, full: str) -> Slot:
        self.settable(full)
        return self.ctx.structure.layout.slots[full]
