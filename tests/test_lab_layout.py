"""The lab (mam_lab/) stays out of the processes: no module under services/ imports it at module
level (the command line imports it inside the commands that need it), and the process commands
load neither the lab nor matplotlib."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _lab_imports(tree: ast.AST, top_level_only: bool) -> list[int]:
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    lines = []
    for node in nodes:
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "mam_lab" for a in node.names):
            lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "mam_lab":
            lines.append(node.lineno)
    return lines


def test_services_import_the_lab_only_lazily_in_the_cli():
    for path in sorted((ROOT / "services").rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        top, anywhere = _lab_imports(tree, True), _lab_imports(tree, False)
        assert not top, f"{path.relative_to(ROOT)}:{top} imports mam_lab at module level"
        if path.parent.name != "cli":
            assert not anywhere, f"{path.relative_to(ROOT)}:{anywhere} imports mam_lab"


@pytest.mark.parametrize("module", ["worker", "referee", "learner", "monitor"])
def test_process_commands_load_neither_the_lab_nor_matplotlib(module: str):
    code = (f"import sys, services.roles.{module}; "
            "print(sorted(m for m in ('mam_lab', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"
