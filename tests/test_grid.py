"""Grids and their plan (mam_lab/grid.py): seeds, variants, grid files, named variants."""

from __future__ import annotations

from pathlib import Path

import pytest

from mam_lab.grid import GridError, load_grid_file, make_grid, parse_seeds, plan, seeds_text, variants
from tests.lab_fixtures import (
    ROOT,
)


def test_parse_seeds():
    assert parse_seeds(3) == (0, 1, 2)
    assert parse_seeds("3") == (0, 1, 2)
    assert parse_seeds("5-7") == (5, 6, 7)
    assert parse_seeds("0-2,9") == (0, 1, 2, 9)
    assert parse_seeds([4, 2]) == (4, 2)
    for bad in ("0,0", "x", 0, "3-1", True):
        with pytest.raises(GridError):
            parse_seeds(bad)
    assert seeds_text([0, 1, 2, 3, 7, 9, 10]) == "0-3,7,9-10"



def test_plan_expands_the_grid():
    grid = make_grid(envs="Hopper-v5,Ant-v5", algos="ma-td3,td3", seeds="2", steps=5000, ablations="no-ot,no-wt",
                     etas="0.05,0.1", flags={"actors": 4, "hidden": "32,32", "batch_size": 64},
                     file={"algo": {"td3": {"start-steps": 100}, "ma-td3": {"actors": 3, "eliminate-at": 2000}}})
    specs = plan(grid)
    kept, aliases = variants(grid)
    assert [v for v, _, _ in kept] == ["ma-td3", "ma-td3-no-ot", "ma-td3-no-wt", "ma-td3-eta0.05", "td3"]
    assert aliases == {"ma-td3-eta0.1": "ma-td3"}  # η = 0.1 is MA-TD3's default: run once
    assert len(specs) == 5 * 2 * 2
    # seed by seed, then env, then variant
    assert [(s.seed, s.env, s.variant) for s in specs[:6]] == [
        (0, "Hopper-v5", "ma-td3"), (0, "Hopper-v5", "ma-td3-no-ot"), (0, "Hopper-v5", "ma-td3-no-wt"),
        (0, "Hopper-v5", "ma-td3-eta0.05"), (0, "Hopper-v5", "td3"), (0, "Ant-v5", "ma-td3")]
    assert specs[-1].path == Path("Ant-v5/td3/seed1")
    assert {s.steps for s in specs} == {5000}  # one budget for every algorithm
    cfg = {(s.env, s.variant, s.seed): s.run_config("t").algo for s in specs}
    ma, td3 = cfg[("Hopper-v5", "ma-td3", 0)], cfg[("Hopper-v5", "td3", 1)]
    assert (ma.actors, ma.eliminate_at, ma.hidden, ma.batch_size, ma.eta, ma.seed) == (4, 2000, (32, 32), 64, 0.1, 0)
    # multi-actor flags from the command line do not reach TD3; the common ones and its own do
    assert (td3.actors, td3.workers, td3.hidden, td3.batch_size, td3.start_steps, td3.seed) == (1, 1, (32, 32), 64,
                                                                                             100, 1)
    assert cfg[("Ant-v5", "ma-td3-no-ot", 1)].no_ot and not cfg[("Ant-v5", "ma-td3", 1)].no_ot
    assert cfg[("Ant-v5", "ma-td3-no-wt", 1)].effective_eta == 0.0
    assert cfg[("Ant-v5", "ma-td3-eta0.05", 1)].eta == 0.05



def test_ddpg_ablations_that_change_nothing_are_not_run_twice():
    grid = make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds=1, steps=1000, ablations="no-wt,no-ot",
                     etas="0,0.1")
    kept, aliases = variants(grid)
    # MA-DDPG has η = 0: without weighting it is the same algorithm
    assert [v for v, _, _ in kept] == ["ma-ddpg", "ma-ddpg-no-ot", "ma-ddpg-eta0.1", "ddpg"]
    assert aliases == {"ma-ddpg-no-wt": "ma-ddpg", "ma-ddpg-eta0": "ma-ddpg"}



def test_grid_errors():
    ok = dict(envs="Hopper-v5", algos="td3", steps=100)
    for bad in (dict(algos="ppo"), dict(envs=""), dict(steps=0), dict(steps=None), dict(ablations="no-xy"),
                dict(etas="1.5"), dict(seeds="a"), dict(flags={"bogus": 1}), dict(flags={"seed": 3}),
                dict(algos="td3,td3")):
        with pytest.raises(GridError):
            make_grid(**{**ok, **bad})
    with pytest.raises(GridError, match="variant"):
        plan(make_grid(**ok, flags={"batch_size": 0}))



def test_grid_files_in_deploy():
    fig1 = make_grid(load_grid_file(ROOT / "deploy/experiments/applecollect-fig1.toml"))
    specs = plan(fig1)
    assert len(specs) == 20 and {s.variant for s in specs} == {"ma-ddpg", "ddpg"}
    ma = next(s for s in specs if s.variant == "ma-ddpg").run_config("t").algo
    dd = next(s for s in specs if s.variant == "ddpg").run_config("t").algo
    assert (ma.actors, ma.workers, ma.eliminate_at, ma.compete_every) == (3, 5, 15000, 1000)
    assert (dd.actors, dd.workers) == (1, 1) and ma.eval_episodes == dd.eval_episodes == 20
    small = make_grid(load_grid_file(ROOT / "deploy/experiments/halfcheetah-small.toml"))
    specs = plan(small)
    assert len(specs) == 4 * 5 and {s.steps for s in specs} == {300_000}
    assert {s.variant for s in specs} == {"ma-td3", "td3", "ma-td3-no-ot", "ma-td3-no-wt"}
    full = make_grid(load_grid_file(ROOT / "deploy/experiments/paper-full.toml"))
    specs = plan(full)
    assert len(specs) == 8 * 4 * 10 and {s.steps for s in specs} == {1_000_000}
    # the command line wins over the file
    reduced = make_grid(load_grid_file(ROOT / "deploy/experiments/applecollect-fig1.toml"), seeds="3",
                        steps=20000, flags={"eliminate_at": 9000})
    specs = plan(reduced)
    assert len(specs) == 6 and specs[0].run_config("t").algo.eliminate_at == 9000



def test_evidence_b_grid_per_env_seeds_and_order():
    grid = make_grid(load_grid_file(ROOT / "deploy/experiments/evidence-b-table4.toml"))
    specs = plan(grid)
    # 5 HalfCheetah seeds and 10 Hopper seeds, 3 arms each: 45 runs, every HalfCheetah run first
    assert len(specs) == 3 * 5 + 3 * 10
    assert [s.env for s in specs] == ["HalfCheetah-v5"] * 15 + ["Hopper-v5"] * 30
    assert [(s.seed, s.variant) for s in specs[:4]] == [(0, "td3"), (0, "ma-td3"), (0, "ma-td3-equal-data"),
                                                        (1, "td3")]
    assert {s.seed for s in specs if s.env == "Hopper-v5"} == set(range(10))
    assert {s.steps for s in specs} == {100_000}
    ma = next(s for s in specs if s.variant == "ma-td3").run_config("t").algo
    eq = next(s for s in specs if s.variant == "ma-td3-equal-data").run_config("t").algo
    td3 = next(s for s in specs if s.variant == "td3").run_config("t").algo
    assert (ma.eliminate_at, ma.compete_every, ma.start_steps, ma.eval_every, ma.eval_episodes) == (
        30000, 5000, 10000, 5000, 10)
    assert (ma.schedule, eq.schedule, eq.eliminate_at) == ("paper", "equal-data", 30000)
    assert (td3.actors, td3.workers, td3.start_steps, td3.eval_every, td3.eval_episodes) == (1, 1, 10000, 5000, 10)
    assert grid.to_dict()["env_seeds"] == {"Hopper-v5": list(range(10))} and grid.to_dict()["order"] == "env"
    # --seeds on the command line applies to every env
    assert len(plan(make_grid(load_grid_file(ROOT / "deploy/experiments/evidence-b-table4.toml"), seeds="2"))) == 12



def test_env_seeds_and_order_seed_by_seed(tmp_path):
    f = tmp_path / "g.toml"
    f.write_text('envs = ["Hopper-v5", "Ant-v5"]\nalgos = ["td3"]\nsteps = 10\nseeds = 2\n'
                 '[env-seeds]\n"Ant-v5" = "0-3"\n')
    specs = plan(make_grid(load_grid_file(f)))
    # the default order: seed by seed, each env only its own seeds
    assert [(s.seed, s.env) for s in specs] == [(0, "Hopper-v5"), (0, "Ant-v5"), (1, "Hopper-v5"), (1, "Ant-v5"),
                                                (2, "Ant-v5"), (3, "Ant-v5")]
    f.write_text('envs = ["Hopper-v5"]\nalgos = ["td3"]\nsteps = 10\n[env-seeds]\n"Ant-v5" = 3\n')
    with pytest.raises(GridError, match="not one of the grid's envs"):
        make_grid(load_grid_file(f))
    f.write_text('envs = ["Hopper-v5"]\nalgos = ["td3"]\nsteps = 10\norder = "random"\n')
    with pytest.raises(GridError, match="order"):
        make_grid(load_grid_file(f))



def test_grid_file_rejects_unknown_keys(tmp_path):
    f = tmp_path / "g.toml"
    f.write_text('envs = ["Hopper-v5"]\nalgos = ["td3"]\nsteps = 10\nactors = 3\n')
    with pytest.raises(GridError, match="unknown key"):
        load_grid_file(f)
    f.write_text('envs = ["Hopper-v5"]\nalgos = ["td3"]\nsteps = 10\n[algo.td3]\nnope = 1\n')
    with pytest.raises(GridError, match="nope"):
        make_grid(load_grid_file(f))


def test_a_top_level_seed_is_told_the_grid_dimension(tmp_path):
    """`seed = 3` at the top of a grid file: seeds are a grid dimension, not a run option."""
    f = tmp_path / "g.toml"
    f.write_text('envs = ["Hopper-v5"]\nalgos = ["td3"]\nsteps = 10\nseed = 3\n')
    with pytest.raises(GridError, match="'seed': the grid dimension is 'seeds'") as e:
        load_grid_file(f)
    assert "algorithm options" not in str(e.value)



def test_named_variants_in_a_grid_file(tmp_path):
    f = tmp_path / "g.toml"
    f.write_text("""
envs = ["Hopper-v5"]
algos = ["td3"]
seeds = 2
steps = 5000
[common]
eval-every = 1000
[algo.ma-td3]
eliminate-at = 2000
[variant.ma-td3-late]
algo = "ma-td3"
eliminate-at = 4000
[variant.ma-td3-no-wt-early]
algo = "ma-td3"
no-wt = true
eliminate_at = 1000
[variant.ma-td3]
algo = "ma-td3"
""")
    grid = make_grid(load_grid_file(f))
    kept, aliases = variants(grid)
    assert [v for v, _, _ in kept] == ["td3", "ma-td3-late", "ma-td3-no-wt-early", "ma-td3"]
    specs = plan(grid)
    assert len(specs) == 8 and specs[0].path == Path("Hopper-v5/td3/seed0")
    cfg = {s.variant: s.run_config("t").algo for s in specs if s.seed == 1}
    assert (cfg["ma-td3-late"].eliminate_at, cfg["ma-td3-late"].eval_every, cfg["ma-td3-late"].actors) == (
        4000, 1000, 2)
    assert cfg["ma-td3-no-wt-early"].effective_eta == 0.0 and cfg["ma-td3-no-wt-early"].eliminate_at == 1000
    assert cfg["ma-td3"].eliminate_at == 2000  # [algo.ma-td3] reaches a variant of that algo
    assert (cfg["td3"].actors, cfg["td3"].eval_every) == (1, 1000)
    # the command line sits below the variant's own flags
    grid = make_grid(load_grid_file(f), flags={"eliminate_at": 3000, "batch_size": 64})
    cfg = {s.variant: s.run_config("t").algo for s in plan(grid)}
    assert cfg["ma-td3-late"].eliminate_at == 4000 and cfg["ma-td3"].eliminate_at == 3000
    assert cfg["ma-td3-late"].batch_size == 64
    # --variants: a subset of the rows
    grid = make_grid(load_grid_file(f), variants="td3,ma-td3-late")
    assert {s.variant for s in plan(grid)} == {"td3", "ma-td3-late"}
    assert grid.to_dict()["variants"]["ma-td3-late"] == {"algo": "ma-td3", "eliminate_at": 4000}



def test_named_variant_errors(tmp_path):
    base = 'envs = ["Hopper-v5"]\nsteps = 100\n'
    for body, match in (('[variant.x]\neliminate-at = 5\n', "algo"),
                        ('[variant.x]\nalgo = "ppo"\n', "algo"),
                        ('[variant.x]\nalgo = "ma-td3"\nbogus = 1\n', "bogus"),
                        ('[variant."a b"]\nalgo = "td3"\n', "variant name"),
                        ('algos = ["td3"]\n[variant.td3]\nalgo = "td3"\nbatch-size = 8\n', "already"),
                        ('', "no algos")):
        f = tmp_path / "g.toml"
        f.write_text(base + body)
        with pytest.raises(GridError, match=match):
            make_grid(load_grid_file(f))
    f.write_text(base + '[variant.x]\nalgo = "td3"\n')
    with pytest.raises(GridError, match="unknown variant"):
        make_grid(load_grid_file(f), variants="y")
    # a variant whose options are invalid fails at planning
    f.write_text(base + '[variant.x]\nalgo = "td3"\nbatch-size = 0\n')
    with pytest.raises(GridError, match="variant x"):
        plan(make_grid(load_grid_file(f)))

