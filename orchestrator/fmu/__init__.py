"""The FMU adapter: FMI 2.0 / 3.0 co-simulation FMUs as modules (to be built)."""

from __future__ import annotations

from typing import Any

from ..errors import DynabrainError
from ..module import Module


def make_fmu_module(name: str, fmu: str, *, base_dir: str, params: dict[str, Any], targets: list[str],
                    isolate: bool = False) -> Module:
    """A module for the FMU at ``fmu`` (a ``.fmu`` file or a source folder, relative to ``base_dir``)."""
    raise DynabrainError(f"module {name!r}: FMU modules need the FMU adapter, which this version does not have yet")
