"""The codebase's own rules: docs that do not drift, no import cycles, small modules, an engine that
names no stage (issue 56's must-shows, checked on every CI run)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("pipeline", "stages", "schemas")
ENGINE = ("pipeline/engine.py", "pipeline/executor.py", "pipeline/cache.py", "pipeline/publish.py")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            rel = p.relative_to(ROOT).with_suffix("")
            name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
            out[name] = p
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Modules of the tree that ``name`` imports (absolute and relative, module level or not)."""
    found = set()
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            cands = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - node.level + 1] + ([base] if base else []))
            cands = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for c in cands:
            while c and c not in known:
                c = c.rpartition(".")[0]
            if c and c != name:
                found.add(c)
    return found


def test_docs_config_md_is_generated_from_the_config_models():
    from pipeline.config_doc import render
    assert (ROOT / "docs" / "config.md").read_text() == render(), \
        "docs/config.md is stale: run `python3 -m pipeline.config_doc > docs/config.md`"


def test_readme_is_a_short_manual():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines"
    long = [i + 1 for i, line in enumerate(lines) if len(line) > 200]
    assert not long, f"README.md lines over 200 characters: {long}"


def test_no_import_cycle():
    mods = _modules()
    graph = {m: _imports(m, p, set(mods)) for m, p in mods.items()}
    # a package's __init__ is imported by its submodules' imports; only module-to-module edges count
    graph = {m: {d for d in deps if not m.startswith(d + ".")} for m, deps in graph.items()}
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in graph[m]:
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " → ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2
    for m in sorted(graph):
        if m not in state:
            visit(m)


@pytest.mark.parametrize("folder,limit", [("pipeline", 400), ("stages", 700), ("schemas", 700), ("tests", 700),
                                          ("bench", 700), ("scripts", 700)])
def test_modules_stay_small(folder, limit):
    big = {str(p.relative_to(ROOT)): n for p in (ROOT / folder).rglob("*.py")
           if (n := len(p.read_text().splitlines())) > limit}
    assert not big, f"modules over {limit} lines: {big}"


def test_the_engine_names_no_stage():
    from pipeline.graph import mould_graph
    g = mould_graph()
    names = {s.name for s in g.stages} | {s.name for s in g.repeat.stages}
    for rel in ENGINE:
        strings = {n.value for n in ast.walk(ast.parse((ROOT / rel).read_text()))
                   if isinstance(n, ast.Constant) and isinstance(n.value, str)}
        idents = {n.id for n in ast.walk(ast.parse((ROOT / rel).read_text())) if isinstance(n, ast.Name)}
        assert not (strings | idents) & names, f"{rel} names stages {sorted((strings | idents) & names)}"
