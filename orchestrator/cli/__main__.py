"""``python -m dynabrain.orchestrator.cli``: the ``dynabrain`` command."""

from .main import main

main()
