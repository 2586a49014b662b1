"""The World and its parts: `World` (`facade`) is the brain's class; `context` is the state its parts
share; `stepper`, `timeline`, `wiring`, `scene`, `names`, `drive`, `transfer` and `realtime` do the
work. Nothing outside this package reaches into the parts but through `World.parts` (benches, tools)."""

from .context import ScheduledAction
from .facade import KEYFRAME_EVERY, World
from .util import BODY_FIELDS, as_connection, expand_names, module_spec

__all__ = ["BODY_FIELDS", "KEYFRAME_EVERY", "ScheduledAction", "World", "as_connection", "expand_names",
           "module_spec"]
