"""The third-party modules the code imports are the ones ``pyproject.toml`` declares.

A package installed by hand on a developer's machine (or CI's) hides a missing declaration until a
user installs into a fresh virtualenv; this test reads every import statement of the tree instead.
"""
import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OWN = {"pipeline", "stages", "schemas", "tests", "bench", "scripts"}
OWN |= {p.stem for folder in ("bench", "scripts") for p in (ROOT / folder).glob("*.py")}  # run as scripts
# modules that runtime code needs but reaches only through another package (trimesh imports
# networkx lazily inside repair.fix_normals): declared, and checked importable here
INDIRECT = {"networkx"}


def _declared() -> dict[str, set[str]]:
    """{group: normalised distribution names}: 'run' for dependencies, one per optional extra."""
    proj = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    name = lambda req: re.split(r"[\s<>=!~\[;]", req, maxsplit=1)[0].lower().replace("_", "-")  # noqa: E731
    out = {"run": {name(r) for r in proj["dependencies"]}}
    for extra, reqs in proj.get("optional-dependencies", {}).items():
        out[extra] = {name(r) for r in reqs}
    return out


def _imports(folders) -> dict[str, list[str]]:
    """{top-level module: [file:line, ...]} of every absolute import under ``folders``."""
    found: dict[str, list[str]] = {}
    for folder in folders:
        for path in sorted((ROOT / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            local = {p.stem for p in path.parent.glob("*.py")}
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    mods = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    mods = [node.module]
                else:
                    continue
                for m in mods:
                    top = m.split(".")[0]
                    if top in OWN or top in local or top in sys.stdlib_module_names or top == "__future__":
                        continue
                    found.setdefault(top, []).append(f"{path.relative_to(ROOT)}:{node.lineno}")
    return found


def _distributions(module: str) -> set[str]:
    return {d.lower().replace("_", "-") for d in packages_distributions().get(module, [])}


def _undeclared(folders, allowed: set[str]) -> list[str]:
    bad = []
    for module, where in sorted(_imports(folders).items()):
        dists = _distributions(module)
        if not dists:   # an extra not installed here (opencamlib for scripts/): its own name
            if module.lower() not in allowed:
                bad.append(f"{module} (not installed, not declared; imported at {where[0]})")
        elif not dists & allowed:
            bad.append(f"{module} from {sorted(dists)} (imported at {where[0]})")
    return bad


def test_the_package_imports_only_declared_runtime_dependencies():
    deps = _declared()
    assert _undeclared(["pipeline", "stages", "schemas"], deps["run"]) == []


def test_tests_benchmarks_and_scripts_import_only_declared_dependencies():
    deps = _declared()
    allowed = set().union(*deps.values())
    assert _undeclared(["tests", "bench", "scripts"], allowed) == []


def test_indirect_runtime_dependencies_are_declared_and_importable():
    import importlib
    deps = _declared()
    for module in INDIRECT:
        assert _distributions(module) & deps["run"], f"{module} is not in pyproject.toml's dependencies"
        importlib.import_module(module)


def test_the_scan_sees_a_missing_declaration():
    # the check itself can fail: numpy, imported everywhere, is not allowed by an empty set
    assert any(b.startswith("numpy") for b in _undeclared(["stages"], set()))
