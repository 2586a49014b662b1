"""YAML with line numbers: plain Python data plus a map from each value's path to its line."""

from __future__ import annotations

from typing import Any

import yaml

from .errors import Problem

Path = tuple[str | int, ...]


class YamlSource:
    """A parsed YAML document that remembers where every value was written."""

    def __init__(self, text: str, file: str):
        self.text = text
        self.file = file
        self.lines: dict[Path, int] = {}
        self.problems: list[Problem] = []
        try:
            node = yaml.compose(text, Loader=yaml.SafeLoader)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            line = mark.line + 1 if mark is not None else None
            reason = getattr(exc, "problem", None) or str(exc)
            self.problems.append(Problem(f"malformed YAML: {reason}", file, line))
            self.data: Any = None
            return
        self._loader = yaml.SafeLoader("")
        self.data = self._build(node, ()) if node is not None else None

    def _build(self, node: yaml.Node, path: Path) -> Any:
        self.lines[path] = node.start_mark.line + 1
        if isinstance(node, yaml.MappingNode):
            out: dict[str, Any] = {}
            for key_node, value_node in node.value:
                key = self._loader.construct_object(key_node, deep=True)
                if not isinstance(key, str):
                    key = str(key)
                if key in out:
                    self.problems.append(Problem(f"key {key!r} is written twice", self.file,
                                                 key_node.start_mark.line + 1, self.field(path)))
                out[key] = self._build(value_node, (*path, key))
                self.lines.setdefault((*path, key), key_node.start_mark.line + 1)
            return out
        if isinstance(node, yaml.SequenceNode):
            return [self._build(item, (*path, i)) for i, item in enumerate(node.value)]
        return self._loader.construct_object(node, deep=True)

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
