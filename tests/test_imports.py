"""The import graph of fojax/: no circle, and no private name taken from another module
(what another module needs is public where it lives). Every import counts, those
inside functions too."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ((ROOT / "fojax", "fojax"), (ROOT / "optimize", "fojax.optimize"))

KNOWN_CIRCLES: set = set()
KNOWN_PRIVATE: tuple = ()


def _modules() -> dict[str, Path]:
    found = {}
    for base, package in PACKAGES:
        for path in base.rglob("*.py"):
            parts = [package, *path.relative_to(base).with_suffix("").parts]
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _imports(module: str, path: Path, modules: dict) -> tuple[set, list]:
    """(modules of fojax ``module`` imports, private names it imports from others)."""

    def owner(name):
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found, private = set(), []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(owner(a.name) for a in node.names if a.name.startswith("fojax"))
        elif isinstance(node, ast.ImportFrom):
            base = package
            for _ in range(max(node.level - 1, 0)):
                base = base.rpartition(".")[0]
            source = (
                (f"{base}.{node.module}" if node.module else base) if node.level else node.module
            )
            if not (source or "").startswith("fojax"):
                continue
            for alias in node.names:
                full = f"{source}.{alias.name}"
                found.add(full if full in modules else owner(source))
                if full not in modules and alias.name.startswith("_"):
                    private.append(f"{module}: {alias.name} from {source}")
    found.discard(None)
    found.discard(module)
    return found, private


def _circles(edges: dict) -> list[set]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, circles, counter = {}, {}, [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while not component or v not in component:
                component.add(stack.pop())
            if len(component) > 1:
                circles.append(component)

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return circles


def test_no_import_circle_and_no_private_import():
    modules = _modules()
    edges, private = {}, []
    for module, path in modules.items():
        edges[module], names = _imports(module, path, modules)
        private += [p for p in names if not p.startswith(KNOWN_PRIVATE)]
    circles = [c for c in _circles(edges) if frozenset(c) not in KNOWN_CIRCLES]
    assert not circles, f"import circles: {circles}"
    assert not private, f"private names imported from another module: {private}"
