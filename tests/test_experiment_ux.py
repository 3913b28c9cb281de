"""`mam experiment` for a user (issue 29): it writes outside the source tree, counts one unit per
figure, prints tables that survive a pipe, and its grid file format is documented."""

import io
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from rich.console import Console

from mam_lab.grid import load_grid_file, make_grid, plan
from mam_lab.tables import print_table
from mam_lab.view import budget_text, describe_plan
from tests.e2e import ROOT

GRID_README = ROOT / "deploy" / "experiments" / "README.md"


def _example() -> str:
    return re.search(r"```toml\n(.*?)```", GRID_README.read_text(), re.S).group(1)


def test_the_documented_example_grid_plans_and_names_every_key(tmp_path: Path):
    path = tmp_path / "my-grid.toml"
    path.write_text(_example())
    grid = make_grid(load_grid_file(path))
    specs = plan(grid)
    assert grid.name == "my-grid" and {s.variant for s in specs} == {"td3", "ma-td3", "ma-td3-equal-data"}
    assert sorted({s.seed for s in specs if s.env == "Hopper-v5"}) == [0, 1, 2, 3, 4]
    table = GRID_README.read_text()
    from mam_lab.grid import GRID_KEYS
    for key in GRID_KEYS:  # every key the loader takes is in the table
        assert f"`{key.replace('_', '-')}`" in table or f"`[{key.replace('_', '-')}" in table, key


def test_the_evidence_grids_name_their_ledger_under_docs_results():
    for path in sorted((ROOT / "deploy" / "experiments").glob("evidence-*.toml")):
        data = load_grid_file(path)
        assert data["ledger"] == f"docs/results/{data['name']}/runs", path
    for path in sorted((ROOT / "deploy" / "experiments").glob("*.toml")):
        if not path.name.startswith("evidence-"):
            assert "ledger" not in tomllib.loads(path.read_text()), path  # a user's grid keeps none


def test_the_plan_says_iterations_and_transitions_and_the_bar_counts_transitions():
    grid = make_grid({}, envs="AppleCollect-v1", algos="ma-ddpg,ddpg", seeds="1", steps=600,
                     flags={"eliminate_at": 300, "compete_every": 100, "start_steps": 100})
    ma, single = plan(grid)
    assert (ma.steps, ma.transitions, single.transitions) == (600, 300 * 5 + 300, 600)
    assert budget_text(ma) == "600 iterations (1,800 transitions)"
    equal = plan(make_grid({}, envs="AppleCollect-v1", algos="ma-ddpg", seeds="1", steps=600,
                           flags={"schedule": "equal-data", "eliminate_at": 300}))[0]
    assert equal.transitions == 600 and budget_text(equal) == "600 transitions"


def test_tables_piped_into_a_file_are_markdown_one_line_per_row(tmp_path: Path):
    out = io.StringIO()
    console = Console(file=out, width=40, force_terminal=False)
    console.soft_wrap = True
    header = ("variant", "deployed final return ± std", "transitions", "wall s (launcher)")
    print_table(console, "HalfCheetah-v5 (x-axis transitions)", header,
                [["ma-td3-train-critics", "4,321.5 ± 1,234.5", "160,000", "1,234"]], fold=True)
    lines = out.getvalue().splitlines()
    assert "| variant | deployed final return ± std | transitions | wall s (launcher) |" in lines
    assert "| ma-td3-train-critics | 4,321.5 ± 1,234.5 | 160,000 | 1,234 |" in lines
    out = io.StringIO()
    grid = make_grid({}, envs="AppleCollect-v1", algos="ma-ddpg", seeds="1", steps=600)
    describe_plan(plan(grid), {}, tmp_path / "exp", Console(file=out, width=40, force_terminal=False, soft_wrap=True))
    row = next(line for line in out.getvalue().splitlines() if line.startswith("| AppleCollect-v1"))
    assert "600 iterations (" in row and row.endswith("|"), out.getvalue()


@pytest.mark.slow  # ~10 s of real processes: the fast suite stays under 5 minutes on 2 cores
def test_an_experiment_without_ledger_leaves_the_checkout_clean(tmp_path: Path):
    """A user's grid, run from a fresh clone without --ledger: everything lands in
    runs/experiments/<name> (ignored by git), nothing in docs/results; `git status` stays empty."""
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--depth", "1", f"file://{ROOT}", str(clone)], check=True, timeout=120)
    mam = Path(sys.executable).parent / "mam"  # the working tree's code (editable install), not the clone's
    env = dict(os.environ, COLUMNS="200", PYTHONWARNINGS="ignore", PYTHONSAFEPATH="1")  # children too
    proc = subprocess.run(
        [str(mam), "experiment", "--name", "user-grid", "--envs", "AppleCollect-v1", "--algos", "ddpg",
         "--seeds", "1", "--steps", "300", "--start-steps", "100", "--hidden", "16,16", "--batch-size", "16",
         "--eval-every", "100", "--eval-episodes", "1", "--no-plot", "--parallel", "1"],
        cwd=clone, env=env, text=True, capture_output=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "no ledger" in proc.stdout, proc.stdout
    exp = clone / "runs" / "experiments" / "user-grid"
    assert (exp / "AppleCollect-v1" / "ddpg" / "seed0" / "summary.json").is_file(), proc.stdout
    assert (exp / "report.md").is_file()
    assert not (clone / "docs" / "results" / "user-grid").exists()
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=clone, text=True,
                            capture_output=True, check=True).stdout
    assert status == "", status
    assert "300 iterations (300 transitions)" in proc.stdout and " steps " not in proc.stdout, proc.stdout
