"""Write what is generated from the bridge's protocol (`protocol.TABLE` and the message models):
``python -m dynabrain.bridge.schema`` writes ``protocol.schema.json`` and the table of calls in
``PROTOCOL.md``, both beside this file; ``python -m dynabrain.bridge.schema PATH`` writes the schema to
PATH only. Tests check the shipped files are up to date."""

from __future__ import annotations

import argparse
import json
import os

from . import protocol as p

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_PATH = os.path.join(HERE, "protocol.schema.json")
DOC_PATH = os.path.join(HERE, "PROTOCOL.md")
TABLE_BEGIN = ("<!-- the table of calls: generated from protocol.TABLE by `python -m dynabrain.bridge.schema`; "
               "edit the table there, not here -->")
TABLE_END = "<!-- end of the table of calls -->"


def render() -> str:
    return json.dumps(p.schema(), indent=2) + "\n"


def calls_table() -> str:
    """The table of calls in Markdown: name, arguments, result, and notes (read-only, long)."""
    lines = ["| call | args | result | notes |", "|---|---|---|---|"]
    for name, call in p.TABLE.items():
        notes = ", ".join(note for note, on in (("read-only", call.read_only), ("long", call.slow)) if on)
        lines.append(f"| `{name}` | {_cell(call.takes)} | {_cell(call.returns)} | {notes} |")
    return "\n".join(lines) + "\n"


def render_doc(text: str) -> str:
    """``PROTOCOL.md``'s text with the part between its table markers written from `protocol.TABLE`."""
    start, end = text.find(TABLE_BEGIN), text.find(TABLE_END)
    if start < 0 or end < start:
        raise ValueError(f"PROTOCOL.md has no table of calls to write (the markers {TABLE_BEGIN!r} and "
                         f"{TABLE_END!r}, in that order)")
    return text[:start + len(TABLE_BEGIN)] + "\n" + calls_table() + text[end:]


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m dynabrain.bridge.schema", description=__doc__)
    parser.add_argument("path", nargs="?", help="write the schema there (and nothing else)")
    path = parser.parse_args(argv).path
    with open(path or DEFAULT_PATH, "w", encoding="utf-8") as fh:
        fh.write(render())
    print(f"wrote {path or DEFAULT_PATH}")
    if path is None:
        with open(DOC_PATH, encoding="utf-8") as fh:
            doc = render_doc(fh.read())
        with open(DOC_PATH, "w", encoding="utf-8") as fh:
            fh.write(doc)
        print(f"wrote the table of calls in {DOC_PATH}")


if __name__ == "__main__":
    main()
