"""The ``dynabrain`` command line, on top of every other room: ``main`` (run, check), ``fmu`` (author
FMUs), ``log`` (run outputs, replay, plot, recover), ``serve`` (the Zenoh bridge). ``python -m
dynabrain.orchestrator.cli`` is the same as ``dynabrain``."""
