"""The lab (mam_lab/) stays out of the processes: no module under services/ imports it at module
level (only the shims that keep the old `python -m services.experiment / experiment_run / bench`
paths working), the process commands load neither the lab nor matplotlib, and the shims run."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHIMS = {"experiment.py", "experiment_run.py", "bench.py"}  # services/<name>: forwards to mam_lab


def _lab_imports(tree: ast.AST, top_level_only: bool) -> list[int]:
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    lines = []
    for node in nodes:
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "mam_lab" for a in node.names):
            lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "mam_lab":
            lines.append(node.lineno)
    return lines


def test_services_import_the_lab_only_in_the_shims_and_lazily_in_the_cli():
    for path in sorted((ROOT / "services").glob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        top, anywhere = _lab_imports(tree, True), _lab_imports(tree, False)
        if path.name in SHIMS:
            assert top, f"{path.name} is a shim: it forwards to mam_lab"
            assert len(path.read_text().splitlines()) <= 15, f"{path.name}: a shim stays tiny"
        else:
            assert not top, f"services/{path.name}:{top} imports mam_lab at module level"
            if path.name != "cli.py":
                assert not anywhere, f"services/{path.name}:{anywhere} imports mam_lab"


@pytest.mark.parametrize("module", ["worker", "referee", "learner", "monitor"])
def test_process_commands_load_neither_the_lab_nor_matplotlib(module: str):
    code = (f"import sys, services.{module}; "
            "print(sorted(m for m in ('mam_lab', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_old_module_paths_still_run():
    env = dict(os.environ, COLUMNS="160", PYTHONWARNINGS="ignore")
    for module, flag in (("services.experiment", "--exp-dir"), ("services.bench", "--only")):
        out = subprocess.run([sys.executable, "-m", module, "--help"], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=120)
        assert out.returncode == 0 and flag in out.stdout, (module, out.stdout + out.stderr)
    # one run of a grid, as grids started by older code start it: no RUN_DIR -> usage, exit status 1
    out = subprocess.run([sys.executable, "-m", "services.experiment_run"], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 1 and "usage: python -m mam_lab.experiment_run RUN_DIR" in out.stderr
