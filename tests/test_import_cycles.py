"""The house has no import cycles: the module-level imports of ``torm`` and ``sim`` form a DAG.

Imports inside functions are deliberate deferrals (optional dependencies, heavy modules) and do not count;
neither do ``if TYPE_CHECKING:`` blocks. ``from pkg import sub`` where ``sub`` is a module is an edge to
``pkg.sub``; importing a module's own ancestor package is implicit in Python and not an edge.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("torm", "sim")


def module_files() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


def _runtime_statements(body: list[ast.stmt]) -> list[ast.stmt]:
    out: list[ast.stmt] = []
    for node in body:
        if isinstance(node, ast.If):
            t = node.test
            if (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
                    isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"):
                continue
            out += _runtime_statements(node.body + node.orelse)
        elif isinstance(node, ast.Try):
            out += _runtime_statements(node.body + [x for h in node.handlers for x in h.body] + node.orelse)
        else:
            out.append(node)
    return out


def import_graph() -> dict[str, set[str]]:
    mods = module_files()

    def owner(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for m, path in mods.items():
        deps: set[str] = set()
        for node in _runtime_statements(ast.parse(path.read_text()).body):
            if isinstance(node, ast.Import):
                deps |= {d for a in node.names if (d := owner(a.name))}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for a in node.names:
                    sub = f"{node.module}.{a.name}"
                    d = sub if sub in mods else owner(node.module)
                    if d:
                        deps.add(d)
        ancestors = {m.rsplit(".", k)[0] for k in range(1, m.count(".") + 1)}
        graph[m] = deps - ancestors - {m}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle (as a module path that returns to its start), or None."""
    state: dict[str, int] = {}  # 1 = on the stack, 2 = done
    stack: list[str] = []

    def visit(v: str) -> list[str] | None:
        state[v] = 1
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state and (c := visit(w)):
                return c
        stack.pop()
        state[v] = 2
        return None

    for v in sorted(graph):
        if v not in state and (c := visit(v)):
            return c
    return None


def test_the_cycle_finder_finds_a_hand_built_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycles_in_torm_and_sim():
    graph = import_graph()
    assert len(graph) > 100 and "torm.reconstruction.dmtet" in graph["torm.reconstruction.api"]
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)
