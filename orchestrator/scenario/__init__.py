"""Scenarios: YAML with lines in, a validated World out. The scenario model and its validation
(`model`), events (`events`), expectations as safe expressions (`expect`), scene specs (`scene`),
modules made from a spec (`make`), and running a scenario to its end (`runner`).

Imports the kernel and the FMU adapter, nothing above.
"""

from .make import ModuleSpecError, make_module
from .model import Scenario, load_scenario, load_world
from .runner import RunResult, run_scenario

__all__ = ["ModuleSpecError", "RunResult", "Scenario", "load_scenario", "load_world", "make_module", "run_scenario"]
