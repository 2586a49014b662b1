"""An SSP's connections made flat: what drives each FMU input once nested systems and the systems' own
connectors are looked through (`ssp.read_ssp`).

An SSP connects connectors: a component's (an FMU variable), or a system's own (an interface of a
nested system, or of the whole system: its inputs, outputs and parameters). A dynabrain scenario has
modules only, so every chain of connections through system connectors is followed to its ends: the
component output that drives it (one at most) and the component inputs and parameters it drives. A
chain with no component output is driven by the whole system's own connector: a parameter's value (a
parameter binding of that system) becomes the driven parameters' value, an input's value is set on the
driven inputs at t=0 (an event), and an input with no value is left to the user (said in the notes).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

Node = tuple[str, tuple[str, ...], str]
"""("c", (flat component name,), connector) for a component's connector, ("j", system path, connector)
for a system's own (the whole system's path is ``()``)."""


@dataclass
class Edge:
    a: Node
    b: Node
    xml: Any
    label: str


@dataclass
class Chain:
    """One group of connected connectors: its component ends and the whole system's connectors in it."""

    edges: list[Edge] = field(default_factory=list)
    components: list[Node] = field(default_factory=list)
    outer: list[Node] = field(default_factory=list)
    """The whole system's own connectors in the chain (path ``()``)."""


def chains(edges: list[Edge]) -> list[Chain]:
    """The connected groups of ``edges`` (union-find over their ends), in the order of their first edge."""
    parent: dict[Node, Node] = {}

    def find(n: Node) -> Node:
        parent.setdefault(n, n)
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for e in edges:
        parent[find(e.a)] = find(e.b)
    groups: dict[Node, Chain] = {}
    for e in edges:
        chain = groups.setdefault(find(e.a), Chain())
        chain.edges.append(e)
        for n in (e.a, e.b):
            if n[0] == "c" and n not in chain.components:
                chain.components.append(n)
            elif n[0] == "j" and n[1] == () and n not in chain.outer:
                chain.outer.append(n)
    return list(groups.values())


def signal(node: Node) -> str:
    """A component node's signal name (``module.port``)."""
    return f"{node[1][0]}.{node[2]}"


def backward_edges(order: list[str], links: list[tuple[str, str]]) -> set[int]:
    """The links (source module, destination module) to delay so that no cycle is left among the rest:
    those that go back (or stay) in ``order`` within a cycle (a strongly connected group of modules)."""
    rank = {m: i for i, m in enumerate(order)}
    graph: dict[str, set[str]] = {}
    for src, dst in links:
        graph.setdefault(src, set()).add(dst)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    group: dict[str, int] = {}
    counter = [0]

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            while True:
                w = stack.pop()
                on.discard(w)
                group[w] = index[v]
                if w == v:
                    break

    for v in order:
        if v not in index:
            visit(v)
    sizes: dict[int, int] = {}
    for g in group.values():
        sizes[g] = sizes.get(g, 0) + 1
    return {i for i, (src, dst) in enumerate(links)
            if group.get(src) == group.get(dst) and (sizes[group[src]] > 1 or src == dst)
            and rank.get(src, 0) >= rank.get(dst, 0)}
