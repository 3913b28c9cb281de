"""The house's layers, read from the source: every import of mam_core/, services/ and mam_lab/ (at
module level, inside functions, under TYPE_CHECKING: each one a reader follows) goes down or
sideways, never up, and no files import each other in a circle.

From the ground up (docs/ARCHITECTURE.md):

1. `mam_core`: the algorithm, pure (no Zenoh, no services).
2. `services/messaging`: key expressions, codecs, the bus.
3. What every process of a run shares: its config, option table, directory, lock, secret,
   announcement, slot binding, CPU and device checks (`services/run/` less the supervision).
4. `services/roles`: the learner, workers, referee, monitor, router and their parts.
5. Run supervision: the launcher, its children (cluster), its progress view, the chaos runner, the
   run's figures.
6. The command line (`services/cli`) and, beside it, `mam_lab`: neither imports the other;
   `services/cli/app.py`, the `mam` command, wires both.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED_RUN = {"config", "rundir", "runlock", "announce", "cpu", "preflight", "registry", "options", "codecheck",
              "secret", "binding"}
TOP = {"services.cli.app", "services.cli.__main__"}

# A circle listed here is known; any other fails. None is left: the roles' circles went with issue
# 39's item 3 (their state is dataclasses that helpers take, learner_state.py and worker_state.py),
# the launcher's with item 4 (the launcher owns its loop; cluster.py supervises the children, and
# progress.py, a view of plain data, imports neither).
KNOWN_CIRCLES: list[set[str]] = []
# Known crossings between the command line and mam_lab, and private names taken across modules:
# none left (mam_lab/bench.py reads the option table in services/run/options.py; bench_sizes.py's
# helpers are public).
KNOWN_CROSSINGS: set[tuple[str, str]] = set()
KNOWN_PRIVATE: set[str] = set()


def layer(module: str) -> int:
    if module.startswith("mam_core"):
        return 1
    if module.startswith("services.messaging"):
        return 2
    if module == "services.run" or module.startswith("services.run.") and module.split(".")[2] in SHARED_RUN:
        return 3
    if module.startswith("services.roles"):
        return 4
    if module.startswith("services.run."):
        return 5
    if module in TOP:
        return 7
    if module.startswith(("services.cli", "mam_lab")):
        return 6
    return 2  # services/__init__.py: it pins the arithmetic (mam_core) before anything computes


def modules() -> dict[str, Path]:
    out = {}
    for top in ("mam_core", "services", "mam_lab"):
        for path in (ROOT / top).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def imports(name: str, path: Path, known: dict[str, Path]) -> dict[str, set[str]]:
    """The project modules `name` imports -> the names it takes from each (empty: the module itself)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: dict[str, set[str]] = {}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [(a.name, "") for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            targets = [(f"{base}.{a.name}", "") if f"{base}.{a.name}" in known else (base, a.name) for a in node.names]
        else:
            continue
        for target, taken in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.setdefault(target, set()).update({taken} - {""})
    return found


def graph() -> dict[str, dict[str, set[str]]]:
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def circles(g: dict[str, dict[str, set[str]]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in g[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(component)

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_no_import_goes_up_a_layer():
    g = graph()
    up = [f"{a} -> {b}" for a, targets in g.items() for b in targets
          if layer(b) > layer(a) and (a, b) not in KNOWN_CROSSINGS]
    assert up == []


def test_the_command_line_and_the_lab_stand_beside_each_other():
    g = graph()
    crossing = [f"{a} -> {b}" for a, targets in g.items() for b in targets
                if layer(a) == layer(b) == 6 and a.split(".")[0] != b.split(".")[0] and (a, b) not in KNOWN_CROSSINGS]
    assert crossing == []


def test_no_new_import_circle():
    found = circles(graph())
    assert [c for c in found if c not in KNOWN_CIRCLES] == []
    assert not any(m.startswith("mam_core") for c in found for m in c)


def test_no_private_name_is_imported_across_modules():
    taken = [f"{a} takes {sorted(n for n in names if n.startswith('_'))} from {b}" for a, targets in graph().items()
             for b, names in targets.items() if any(n.startswith("_") for n in names) and a not in KNOWN_PRIVATE]
    assert taken == []


def test_the_checks_above_can_fail():
    """An import that goes up, a circle and a private name are found in a made-up house."""
    g = {"mam_core.a": {"services.roles.b": set()}, "services.roles.b": {"mam_core.a": {"_hidden"}}}
    assert layer("mam_core.a") < layer("services.roles.b") and circles(g) == [{"mam_core.a", "services.roles.b"}]
    assert layer("services.run.options") < layer("services.roles.learner") < layer("services.run.launcher")
    assert layer("services.run.launcher") < layer("services.cli.eval_command") == layer("mam_lab.grid")
    assert "services.run.progress" in graph()["services.run.launcher"]  # imports are read
