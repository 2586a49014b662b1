"""YAML with line numbers: plain Python data plus a map from each value's path to its line.

A YAML file is read within limits, every one a file:line problem rather than a hang or a traceback:

- `MAX_FILE_BYTES`: the size of the file;
- `MAX_DEPTH`: how deeply lists and mappings nest;
- `MAX_VALUES`: how many values the document holds once its aliases are expanded (nine nested
  anchors of nine items each would expand to 387 million: an "alias bomb");
- the text is UTF-8 (a UTF-8 byte-order mark is allowed); a file in another encoding, or binary
  data, is named with the line of the first byte at fault;
- only the core schema's tags (`CORE_TAGS`: strings, numbers, booleans, null, lists, mappings, and the
  dates YAML reads unasked): ``!!python/name:...``, ``!!binary``, ``!!set`` or a custom ``!tag``, on a
  value, a list or a mapping, is an error with its line, never ignored.

The limits are checked on the parser's event stream before anything is built, so a refused file
costs time in proportion to its size, never to its expansion.
"""

from __future__ import annotations

import codecs
import os
from typing import Any

import yaml

from .errors import Problem

Path = tuple[str | int, ...]

MAX_FILE_BYTES = 2 * 1024 * 1024
"""The largest YAML file read (2 MiB)."""
MAX_DEPTH = 50
"""How deeply lists and mappings may nest."""
MAX_VALUES = 200_000
"""How many values (scalars, lists, mappings) a document may hold, its aliases expanded."""

_YAML = "tag:yaml.org,2002:"
CORE_TAGS = frozenset(_YAML + t for t in ("str", "int", "float", "bool", "null", "seq", "map", "timestamp", "merge"))
"""The tags a value may carry, written or implied (a plain ``2024-01-01`` is a timestamp); any other is refused."""

_WIDE_BOMS = ((codecs.BOM_UTF32_LE, "UTF-32"), (codecs.BOM_UTF32_BE, "UTF-32"),
              (codecs.BOM_UTF16_LE, "UTF-16"), (codecs.BOM_UTF16_BE, "UTF-16"))


def read_yaml(path: str | os.PathLike[str], what: str = "file") -> YamlSource:
    """The YAML file at ``path`` parsed, or a `YamlSource` whose ``problems`` say why not (``what``
    names the file in a message: "the scenario"). The file is read within `MAX_FILE_BYTES`; only a
    regular file is (a link is followed)."""
    file = os.fspath(path)
    try:
        if os.path.exists(file) and not os.path.isfile(file):  # a FIFO would hang the read, a device never end
            return YamlSource.failed(file, Problem(f"cannot read {what}: it is not a regular file", file))
        with open(file, "rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        return YamlSource.failed(file, Problem(f"cannot read {what}: {exc.strerror or exc}", file))
    if len(raw) > MAX_FILE_BYTES:
        line = raw.count(b"\n", 0, MAX_FILE_BYTES) + 1  # where the file passes the limit
        return YamlSource.failed(file, Problem(f"{what} is larger than {MAX_FILE_BYTES // 1024} KiB "
                                               f"(MAX_FILE_BYTES): it passes the limit on this line", file, line))
    text, problem = decode(raw, file)
    if problem is not None:
        return YamlSource.failed(file, problem)
    return YamlSource(text, file)


def decode(raw: bytes, file: str) -> tuple[str, Problem | None]:
    """``raw`` as UTF-8 text, or a problem naming the encoding and the line of the first bad byte."""
    for bom, name in _WIDE_BOMS:
        if raw.startswith(bom):
            return "", Problem(f"the file is {name} text (it starts with a {name} byte-order mark); "
                               "save it as UTF-8", file, 1)
    nul = raw.find(b"\0")
    if nul >= 0:
        return "", Problem("the file holds a NUL byte: binary data or UTF-16/32 text, not UTF-8 YAML",
                           file, raw.count(b"\n", 0, nul) + 1)
    try:
        return raw.decode("utf-8-sig"), None
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        return "", Problem(f"the file is not UTF-8 text: byte 0x{raw[exc.start]:02x} at column {column} "
                           "(Latin-1 or another encoding?); save it as UTF-8", file, line)


class YamlSource:
    """A parsed YAML document that remembers where every value was written."""

    def __init__(self, text: str, file: str):
        self.text = text
        self.file = file
        self.lines: dict[Path, int] = {}
        self.problems: list[Problem] = []
        self.data: Any = None
        try:
            limit = _check_limits(text)
            if limit is not None:
                self.problems.append(Problem(limit[1], file, limit[0]))
                return
            node = yaml.compose(text, Loader=yaml.SafeLoader)
        except yaml.YAMLError as exc:
            self.problems.append(Problem(f"malformed YAML: {_reason(exc)}", file, _line(exc, text)))
            return
        self._loader = yaml.SafeLoader("")
        self.data = self._build(node, ()) if node is not None else None

    @classmethod
    def failed(cls, file: str, problem: Problem) -> YamlSource:
        """A source that could not be read: no data, one problem."""
        src = cls("", file)
        src.problems.append(problem)
        return src

    def _build(self, node: yaml.Node, path: Path) -> Any:
        self.lines[path] = node.start_mark.line + 1
        if node.tag not in CORE_TAGS:
            tag = "!!" + node.tag.removeprefix(_YAML) if node.tag.startswith(_YAML) else node.tag
            self.problems.append(Problem(f"cannot read this value: the YAML tag {tag} is not allowed (only the "
                                         "core schema's: strings, numbers, booleans, null, lists, mappings)", self.file,
                                         node.start_mark.line + 1, self.field(path) or None))
            return None
        if isinstance(node, yaml.MappingNode):
            out: dict[str, Any] = {}
            for key_node, value_node in node.value:
                if not isinstance(key_node, yaml.ScalarNode):
                    self.problems.append(Problem("a key is a plain value, not a list or a mapping", self.file,
                                                 key_node.start_mark.line + 1, self.field(path) or None))
                    continue
                key = self._scalar(key_node, path)
                if not isinstance(key, str):
                    key = str(key)
                if key in out:
                    self.problems.append(Problem(f"key {key!r} is written twice", self.file,
                                                 key_node.start_mark.line + 1, self.field(path) or None))
                out[key] = self._build(value_node, (*path, key))
                self.lines.setdefault((*path, key), key_node.start_mark.line + 1)
            return out
        if isinstance(node, yaml.SequenceNode):
            return [self._build(item, (*path, i)) for i, item in enumerate(node.value)]
        return self._scalar(node, path)

    def _scalar(self, node: yaml.Node, path: Path) -> Any:
        try:
            return self._loader.construct_object(node, deep=True)
        except (yaml.YAMLError, ValueError, OverflowError, TypeError) as exc:
            reason = _reason(exc) if isinstance(exc, yaml.YAMLError) else str(exc).split(";")[0]
            self.problems.append(Problem(f"cannot read this value: {reason}", self.file, node.start_mark.line + 1,
                                         self.field(path) or None))
            return None

    def line(self, path: Path) -> int | None:
        """The line of ``path``, or of its closest written ancestor."""
        path = tuple(path)
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return self.lines.get(())

    @staticmethod
    def field(path: Path) -> str:
        out = ""
        for part in path:
            out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
        return out

    def problem(self, path: Path, message: str) -> Problem:
        return Problem(message, self.file, self.line(path), self.field(path) or None)


def _check_limits(text: str) -> tuple[int, str] | None:
    """(line, message) of the first place ``text`` passes `MAX_DEPTH` or `MAX_VALUES`, read from the
    parser's events (iterative, and linear in the text however far its aliases would expand)."""
    open_sizes: list[list[Any]] = []  # per open list or mapping: [anchor, values inside so far]
    anchors: dict[str, int] = {}
    total = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, yaml.CollectionStartEvent):
            if len(open_sizes) >= MAX_DEPTH:
                return event.start_mark.line + 1, f"lists and mappings nest deeper than {MAX_DEPTH} levels (MAX_DEPTH)"
            open_sizes.append([event.anchor, 1])
            size = 1
        elif isinstance(event, yaml.CollectionEndEvent):
            anchor, size = open_sizes.pop()
            if anchor is not None:
                anchors[anchor] = size
            if open_sizes:
                open_sizes[-1][1] += size
            continue
        elif isinstance(event, yaml.ScalarEvent):
            size = 1
            if event.anchor is not None:
                anchors[event.anchor] = 1
        elif isinstance(event, yaml.AliasEvent):
            if any(anchor == event.anchor for anchor, _ in open_sizes):
                return event.start_mark.line + 1, f"the alias *{event.anchor} is inside its own anchor (a loop)"
            size = anchors.get(event.anchor, 1)
        else:
            continue
        total += size
        if total > MAX_VALUES:
            what = f"the alias *{event.anchor} brings it" if isinstance(event, yaml.AliasEvent) else "it has"
            return event.start_mark.line + 1, (f"the document holds more than {MAX_VALUES} values once its "
                                               f"aliases are expanded (MAX_VALUES); {what} past the limit")
        if open_sizes and not isinstance(event, yaml.CollectionStartEvent):
            open_sizes[-1][1] += size
    return None


def _reason(exc: yaml.YAMLError) -> str:
    return getattr(exc, "problem", None) or str(exc).splitlines()[0]


def _line(exc: yaml.YAMLError, text: str) -> int | None:
    mark = getattr(exc, "problem_mark", None)
    if mark is not None:
        return mark.line + 1
    position = getattr(exc, "position", None)  # a reader error: a character YAML does not allow
    return text.count("\n", 0, position) + 1 if isinstance(position, int) else None
