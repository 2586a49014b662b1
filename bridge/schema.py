"""Write the JSON Schema of the bridge's JSON messages: ``python -m dynabrain.bridge.schema [PATH]``
(default: ``protocol.schema.json`` beside this file). A test checks the shipped file is up to date."""

from __future__ import annotations

import argparse
import json
import os

from .protocol import schema

DEFAULT_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "protocol.schema.json")


def render() -> str:
    return json.dumps(schema(), indent=2) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m dynabrain.bridge.schema", description=__doc__)
    parser.add_argument("path", nargs="?", default=DEFAULT_PATH, help="where to write the schema")
    path = parser.parse_args(argv).path
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(render())
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
