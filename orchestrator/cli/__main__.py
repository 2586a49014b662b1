"""``python -m dynabrain.orchestrator.cli``: the ``dynabrain`` command (only when run as a program:
importing this module runs nothing)."""

from .main import main

if __name__ == "__main__":
    main()
