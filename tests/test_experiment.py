"""`mam experiment` (grid, plan, resume) and `mam report` (IQM, bootstrap, P(improvement), tables)."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from mam_lab.analysis import SUCCESS_RETURN, build_report
from mam_lab.grid import GridError, load_grid_file, make_grid, parse_seeds, plan, seeds_text, variants
from mam_lab.ledger import (
    LEARNER_ROWS,
    check_resume,
    config_mismatch,
    in_ledger,
    run_state,
    thin_indices,
    thin_jsonl,
    write_manifest,
)
from mam_lab.report import write_report
from mam_lab.scheduler import Launch, core_slots, default_parallel, run_grid
from mam_lab.scores import best_live_score, bucket_points, first_reach, last_n_mean
from mam_lab.stats import (
    Interval,
    iqm,
    iqm_ci,
    mean_ci,
    probability_of_improvement,
    probability_of_improvement_ci,
    stratified_bootstrap,
    verdict_word,
    wilson_interval,
)
from mam_lab.tables import bias_rows
from services.run.rundir import write_json

ROOT = Path(__file__).resolve().parents[1]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def quiet() -> Console:
    return Console(file=open(os.devnull, "w"), width=120)


# --- IQM -----------------------------------------------------------------------------------


def test_iqm_hand_computed():
    # n = 8: drop the 2 lowest and 2 highest, mean of 3, 4, 5, 6
    assert iqm([200, 3, 1, 6, 100, 4, 2, 5]) == pytest.approx(4.5)
    # n = 10: the middle half is 5 observations: 4..7 in full, 3 and 8 with weight 1/2
    assert iqm([1, 2, 3, 4, 5, 6, 7, 8, 9, 1000]) == pytest.approx((0.5 * 3 + 4 + 5 + 6 + 7 + 0.5 * 8) / 5)
    # n = 3: weights 1/4, 1, 1/4 over 1.5
    assert iqm([600, 0, 6]) == pytest.approx((0.25 * 0 + 6 + 0.25 * 600) / 1.5)
    assert iqm([7.0]) == 7.0
    assert iqm([2.0, 4.0]) == pytest.approx(3.0)
    # insensitive to outliers, equal to the mean for symmetric data
    assert iqm([-1e9, 1, 2, 3, 4, 5, 6, 1e9]) == pytest.approx(3.5)
    # vectorised along an axis
    np.testing.assert_allclose(iqm(np.array([[200, 3, 1, 6, 100, 4, 2, 5], [1, 1, 1, 1, 2, 2, 2, 2]]), axis=1),
                               [4.5, 1.5])
    with pytest.raises(ValueError):
        iqm([])


def test_iqm_is_the_25_percent_trimmed_mean_for_multiples_of_four():
    rng = np.random.default_rng(3)
    x = rng.normal(size=40)
    s = np.sort(x)
    assert iqm(x) == pytest.approx(s[10:30].mean())


# --- bootstrap -----------------------------------------------------------------------------


def test_bootstrap_is_seeded_and_contains_the_true_value():
    rng = np.random.default_rng(0)
    strata = [rng.normal(5.0, 2.0, size=30) for _ in range(3)]  # symmetric: the true IQM is 5
    a = iqm_ci(strata, n_boot=2000, seed=1)
    b = iqm_ci(strata, n_boot=2000, seed=1)
    c = iqm_ci(strata, n_boot=2000, seed=2)
    assert a == b and a != c
    assert a.lo < a.value < a.hi and a.contains(5.0)
    assert a.value == pytest.approx(iqm(np.concatenate(strata)))
    m = mean_ci(strata[0], seed=0)
    assert m.value == pytest.approx(strata[0].mean()) and m.contains(5.0)


def test_bootstrap_ci_coverage_near_95_percent():
    rng = np.random.default_rng(7)
    hits = 0
    trials = 200
    for t in range(trials):
        strata = [rng.normal(mu, 1.0, size=20) for mu in (0.0, 0.0, 0.0)]
        hits += iqm_ci(strata, n_boot=400, seed=t).contains(0.0)
    assert 0.85 <= hits / trials <= 1.0


def test_stratified_bootstrap_resamples_within_each_stratum():
    # Every replicate keeps 5 draws from each env: the pooled mean is always 5 when one env is all
    # 0 and the other all 10 (a pooled, unstratified bootstrap would vary).
    strata = [np.zeros(5), np.full(5, 10.0)]
    reps = stratified_bootstrap([strata], lambda s: np.concatenate(s, axis=-1).mean(axis=-1), n_boot=500, seed=0)
    assert reps.shape == (500,)
    np.testing.assert_allclose(reps, 5.0)
    # and resampling does vary within a stratum
    reps = stratified_bootstrap([[np.arange(10.0)]], lambda s: s[0].mean(axis=-1), n_boot=500, seed=0)
    assert reps.std() > 0.3


# --- probability of improvement ------------------------------------------------------------


def test_probability_of_improvement_hand_made_scores():
    assert probability_of_improvement([[5, 6, 7]], [[1, 2, 3, 4]]) == 1.0
    assert probability_of_improvement([[1, 2, 3, 4]], [[5, 6, 7]]) == 0.0
    assert probability_of_improvement([[1, 2, 3]], [[1, 2, 3]]) == 0.5
    assert probability_of_improvement([[3.0, 4.0]], [[1.0, 3.5]]) == pytest.approx(0.75)
    assert probability_of_improvement([[1, 2, 3]], [[2, 2]]) == pytest.approx(0.5)  # ties count 1/2
    # averaged over envs: 1.0 on one, 0.0 on the other
    assert probability_of_improvement([[5.0, 6.0], [0.0]], [[1.0], [9.0, 8.0]]) == pytest.approx(0.5)


def test_probability_of_improvement_ci():
    p = probability_of_improvement_ci([[5, 6, 7]], [[1, 2, 3, 4]], n_boot=500, seed=0)
    assert (p.value, p.lo, p.hi) == (1.0, 1.0, 1.0)
    p = probability_of_improvement_ci([[1.0, 2.0, 3.0]], [[1.0, 2.0, 3.0]], n_boot=1000, seed=0)
    assert p.value == 0.5 and p.lo < 0.5 < p.hi
    rng = np.random.default_rng(1)
    p = probability_of_improvement_ci([rng.normal(1, 1, 50), rng.normal(1, 1, 50)],
                                      [rng.normal(0, 1, 50), rng.normal(0, 1, 50)], n_boot=1000, seed=0)
    true = 0.7602  # P(N(1,1) > N(0,1)) = Phi(1/sqrt(2))
    assert p.contains(true)


def test_wilson_interval():
    w = wilson_interval(0, 10)
    assert w.value == 0.0 and w.lo == 0.0 and w.hi == pytest.approx(0.2775, abs=1e-3)
    w = wilson_interval(10, 10)
    assert w.value == 1.0 and w.hi == 1.0 and w.lo == pytest.approx(0.7225, abs=1e-3)
    w = wilson_interval(5, 10)
    assert w.lo == pytest.approx(0.2366, abs=1e-3) and w.hi == pytest.approx(0.7634, abs=1e-3)


# --- scores of run directories -------------------------------------------------------------


def test_best_live_score_and_buckets():
    assert best_live_score({"mean": [3.0, 7.0, None]}) == 7.0
    assert best_live_score({"mean": [None, 5.0]}) == 5.0
    assert best_live_score({"mean": [None, None]}) is None
    assert best_live_score({"returns": [[1.0, 3.0], []]}) == 2.0
    # floor to the grid; the last evaluation of a cell wins (a late round and the final evaluation)
    cells = bucket_points([(50, 1.0), (100, 2.0), (130, 3.0), (1003, 4.0), (1000, 9.0), (1005, 5.0)], 100)
    assert cells == {0: 1.0, 100: 3.0, 1000: 5.0}
    pts = [(s, float(s // 100)) for s in range(100, 2001, 100)]
    assert last_n_mean(pts, 100) == pytest.approx(np.mean(range(11, 21)))
    assert last_n_mean(pts[:3], 100) == pytest.approx(2.0)
    assert np.isnan(last_n_mean([], 100))


SPACING, STEPS = 100, 2000


def write_run(run_dir: Path, algo: str, seed: int, k: int, score, finished: bool = True,
              final: float | None = None) -> None:
    """A run directory as the system writes it: config.json, eval.jsonl, allocation.jsonl, summary.json.

    `score(step)` is the best actor's return; with k > 1 the other actors score 10 less before the
    elimination at C = 1000 (and are not evaluated after it). Multi-actor runs also evaluate at
    every round A = 50 before C (off the grid), and evaluations land 3 steps late.
    """
    run_dir.mkdir(parents=True)
    cfg = {"run": f"r{seed}", "env_id": "Toy-v0", "steps": STEPS,
           "algo": {"algo": algo, "actors": k, "workers": 3 if k > 1 else 1, "eval_every": SPACING,
                    "eliminate_at": 1000, "compete_every": 50, "eta": 0.1 if k > 1 else 0.0, "no_ot": False,
                    "no_wt": False, "seed": seed, "utd": 1.0}}
    (run_dir / "config.json").write_text(json.dumps(cfg))
    rows, allocs = [], []
    steps = list(range(SPACING, STEPS + 1, SPACING))
    if k > 1:  # rounds every A = 50 before the elimination at C = 1000
        steps = sorted(set(steps) | set(range(50, 1000, 50)))
    for i, step in enumerate(steps):
        best = score(step)
        if k > 1 and step < 1000:
            mean = [best - 10.0] * (k - 1) + [best]
            allocs.append({"env_steps": step + 3, "counts": [1] * (k - 1) + [2], "probabilities":
                           [0.2] * (k - 1) + [1 - 0.2 * (k - 1)], "reason": "round", "returns": mean})
        elif k > 1 and step == 1000:  # the elimination's competition: the best actor survives
            allocs.append({"env_steps": step + 3, "probabilities": [0.0] * (k - 1) + [1.0], "reason": "elimination",
                           "returns": [best - 10.0] * (k - 1) + [best], "survivor": k - 1})
        elif k > 1:
            mean = [None] * (k - 1) + [best]
        else:
            mean = [best]
        rows.append({"round": i + 1, "env_steps": step + 3, "mean": mean, "returns": [[m] if m is not None else []
                                                                                      for m in mean]})
    if finished:
        rows.append({"round": 999, "env_steps": STEPS + 3, "mean": rows[-1]["mean"], "returns": []})
    with open(run_dir / "eval.jsonl", "w") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    with open(run_dir / "allocation.jsonl", "w") as f:
        for r in allocs:
            f.write(json.dumps(r) + "\n")
    if finished:
        finals = rows[-1]["mean"] if final is None else [None] * (k - 1) + [final]
        (run_dir / "summary.json").write_text(json.dumps({
            "final_returns": finals, "survivor": k - 1, "env_steps": STEPS + 3, "updates": STEPS - 100,
            "wall_time_s": 10.0 + seed, "launcher_wall_time_s": 20.0 + seed}))


def make_experiment(exp: Path) -> None:
    # ma-td3: score = step/100 + seed (seeds 0, 1, 2); td3: score = step/200 (seeds 0, 1)
    for seed in (0, 1, 2):
        write_run(exp / "Toy-v0" / "ma-td3" / f"seed{seed}", "ma-td3", seed, 2, lambda s, seed=seed: s / 100 + seed)
    for seed in (0, 1):
        write_run(exp / "Toy-v0" / "td3" / f"seed{seed}", "td3", seed, 1, lambda s: s / 200)
    write_run(exp / "Toy-v0" / "td3" / "seed2", "td3", 2, 1, lambda s: 1e6, finished=False)  # interrupted
    planned = [f"Toy-v0/{v}/seed{s}" for s in (0, 1, 2) for v in ("ma-td3", "td3")]
    write_json(exp / "experiment.json", {"name": "toy", "runs": [{"path": p} for p in planned]})


def test_report_statistics_on_synthetic_run_dirs(tmp_path):
    exp = tmp_path / "exp"
    make_experiment(exp)
    report = build_report(exp, n_boot=500)
    assert report.missing == ["Toy-v0/td3/seed2"]
    (ma, td3) = report.envs["Toy-v0"]
    assert (ma.variant, td3.variant) == ("ma-td3", "td3") and (ma.n, td3.n) == (3, 2)
    assert ma.spacing == SPACING
    # last 10 grid points are 1100..2000: mean step/100 = 15.5, plus the seed
    np.testing.assert_allclose(ma.last10, [15.5, 16.5, 17.5])
    np.testing.assert_allclose(td3.last10, [7.75, 7.75])
    assert ma.last10_mean.value == pytest.approx(16.5) and ma.last10_std == pytest.approx(np.std([15.5, 16.5, 17.5]))
    assert ma.iqm.value == pytest.approx(iqm([15.5, 16.5, 17.5]))
    # max average return: mean over seeds peaks at the last point, 20 + mean(0, 1, 2) = 21
    assert ma.max_avg.value == pytest.approx(21.0) and ma.max_avg.step == STEPS
    assert ma.max_avg.std == pytest.approx(np.std([20.0, 21.0, 22.0]))
    assert td3.max_avg.value == pytest.approx(10.0) and td3.max_avg.std == pytest.approx(0.0)
    # the best live actor's score, never the others' (10 lower); the round at 550 is the last
    # evaluation of the grid cell [500, 600)
    assert ma.curves[0, list(ma.grid).index(500)] == pytest.approx(5.5)
    assert ma.updates == STEPS - 100 and ma.wall_time_s == pytest.approx(11.0)
    assert ma.success is None  # only for AppleCollect
    (c,) = report.comparisons
    assert (c.x, c.y, c.env, c.n_x, c.n_y) == ("ma-td3", "td3", "Toy-v0", 3, 2)
    assert c.p.value == 1.0 and c.p.lo == 1.0


def test_report_files_and_apple_collect_success_share(tmp_path):
    exp = tmp_path / "exp"
    env = "AppleCollect-v0"
    finals = {0: 49.96, 1: 9.97, 2: 49.96}
    for seed, final in finals.items():
        write_run(exp / env / "ma-ddpg" / f"seed{seed}", "ma-ddpg", seed, 3, lambda s: s / 100, final=final)
        write_run(exp / env / "ddpg" / f"seed{seed}", "ddpg", seed, 1, lambda s: -1.0, final=-1.0)
    for cfg in exp.rglob("config.json"):
        data = json.loads(cfg.read_text())
        data["env_id"] = env
        cfg.write_text(json.dumps(data))
    report, md, pngs = write_report(exp, n_boot=300)
    ma, ddpg = report.envs[env]
    assert (ma.successes, ma.n, ddpg.successes) == (2, 3, 0)
    assert ma.success.value == pytest.approx(2 / 3)
    text = md.read_text()
    assert md == exp / "report.md"
    assert "| ma-ddpg |" in text and "| ddpg |" in text and "2/3 (67%)" in text and "P(ma-ddpg > ddpg)" in text
    names = {p.name for p in pngs}
    assert names == {"curves_AppleCollect-v0.png", "allocation_AppleCollect-v0.png", "iqm.png"}
    for p in pngs:
        assert p.read_bytes()[:8] == PNG_MAGIC and f"figures/{p.name}" in text


def test_report_aggregates_over_envs(tmp_path):
    exp = tmp_path / "exp"
    for env_i, env in enumerate(("A-v0", "B-v0")):
        for seed in range(3):
            for algo, k, offset in (("ma-td3", 2, 1.0), ("td3", 1, 0.0)):
                d = exp / env / algo / f"seed{seed}"
                write_run(d, algo, seed, k, lambda s, o=offset, e=env_i, sd=seed: (o + 0.1 * sd) * (1 + 100 * e))
                data = json.loads((d / "config.json").read_text())
                data["env_id"] = env
                (d / "config.json").write_text(json.dumps(data))
    report = build_report(exp, n_boot=300)
    assert set(report.envs) == {"A-v0", "B-v0"}
    agg = dict((name, i) for name, _, i in report.aggregate)
    assert agg["ma-td3"].value > agg["td3"].value
    overall = [c for c in report.comparisons if c.env == "all 2 envs"]
    assert len(overall) == 1 and overall[0].p.value == 1.0


# --- grid and plan -------------------------------------------------------------------------


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


# --- running and resuming (real child processes that stand in for a run) --------------------

# A run process as `mam experiment` starts it (see mam_lab/experiment_run.py), with its training
# replaced by a sleep: it takes its affinity from launch.json, writes the files a run writes and
# reports its outcome through its exit status. MODE: ok, fail (exit 3), interrupt (exit 130),
# hang (until SIGTERM, then 130).
FAKE_RUN = r"""
import json, os, signal, sys, time
run_dir, mode, delay = sys.argv[1], sys.argv[2], float(sys.argv[3])
launch = json.load(open(os.path.join(run_dir, "launch.json")))
if launch["cores"]:
    os.sched_setaffinity(0, launch["cores"])
assert not os.path.exists(os.path.join(run_dir, "junk")), "a partial run was not cleared"
cfg = launch["config"]
json.dump(cfg, open(os.path.join(run_dir, "config.json"), "w"))
os.makedirs(os.path.join(run_dir, "logs"))
open(os.path.join(run_dir, "logs", "learner.log"), "w").write("boom" if mode == "fail" else "ok")
t0 = time.time()
if mode == "hang":
    signal.signal(signal.SIGTERM, lambda *a: sys.exit(130))
    print("hanging", flush=True)
    time.sleep(120)
    sys.exit(1)
time.sleep(delay)
if mode == "fail":
    sys.exit(3)
if mode == "interrupt":
    sys.exit(130)
with open(os.path.join(run_dir, "learner.jsonl"), "w") as f:
    for i in range(1000):
        f.write(json.dumps({"env_steps": i, "updates": i}) + "\n")
with open(os.path.join(run_dir, "eval.jsonl"), "w") as f:
    f.write(json.dumps({"env_steps": cfg["steps"], "mean": [1.0]}) + "\n")
os.makedirs(os.path.join(run_dir, "checkpoints"))
open(os.path.join(run_dir, "checkpoints", "learner.pt"), "wb").write(b"x" * 1000)
json.dump({"start": t0, "end": time.time(), "cores": sorted(os.sched_getaffinity(0))},
          open(os.path.join(run_dir, "timing.json"), "w"))
json.dump({"final_returns": [1.0], "survivor": 0, "env_steps": cfg["steps"], "updates": 1, "wall_time_s": 1},
          open(os.path.join(run_dir, "summary.json"), "w"))
"""


class FakeLauncher:
    """Starts FAKE_RUN as the run's process; `modes` gives each successive start its mode (then "ok")."""

    def __init__(self, *modes: str, delay: float = 0.0) -> None:
        self.modes = list(modes)
        self.delay = delay
        self.calls: list[Path] = []
        self.cores: list[tuple[int, ...]] = []

    def __call__(self, job: Launch) -> subprocess.Popen:
        self.calls.append(job.run_dir)
        self.cores.append(job.cores)
        mode = self.modes.pop(0) if self.modes else "ok"
        write_json(job.run_dir / "launch.json", {"config": job.cfg.to_dict(), "cores": list(job.cores) or None})
        return subprocess.Popen([sys.executable, "-c", FAKE_RUN, str(job.run_dir), mode, str(self.delay)],
                                stdout=job.log, stderr=subprocess.STDOUT, start_new_session=True)


def finish_fake(spec, exp: Path) -> None:
    """A finished run directory, as FAKE_RUN leaves it."""
    run_dir = _mkdir(exp / spec.path)
    write_json(run_dir / "launch.json", {"config": spec.run_config("x").to_dict(), "cores": None})
    subprocess.run([sys.executable, "-c", FAKE_RUN, str(run_dir), "ok", "0"], check=True)


def small_grid():
    return make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds="2", steps=300,
                     flags={"hidden": "8,8", "batch_size": 8})


def test_resume_skips_finished_runs_and_redoes_partial_ones(tmp_path):
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    assert [run_state(s, exp) for s in specs] == ["todo"] * 4
    done, partial = specs[0], specs[1]
    finish_fake(done, exp)
    _mkdir(exp / partial.path)
    (exp / partial.path / "junk").write_text("left by an interrupted run")
    assert run_state(done, exp) == "done" and run_state(partial, exp) == "partial"
    check_resume(specs, exp)

    runner = FakeLauncher()
    result = run_grid(specs, exp, quiet(), launcher=runner, cores=[()])
    assert result.skipped == [done] and result.finished == specs[1:] and not result.failed
    assert runner.calls == [exp / s.path for s in specs[1:]]
    assert all(run_state(s, exp) == "done" for s in specs)
    assert (exp / partial.path / "launcher.log").is_file()

    again = FakeLauncher()
    result = run_grid(specs, exp, quiet(), launcher=again, cores=[()])
    assert again.calls == [] and result.skipped == specs and result.finished == []


def test_resume_refuses_finished_runs_of_another_grid(tmp_path):
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    finish_fake(specs[0], exp)
    other = plan(make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds="2", steps=600,
                           flags={"hidden": "8,8", "batch_size": 8}))
    assert config_mismatch(other[0], exp / other[0].path) == ["steps: run 300, grid 600"]
    with pytest.raises(GridError, match="different grid"):
        check_resume(other, exp)


def test_failed_runs_are_retried_and_their_logs_kept(tmp_path):
    specs = plan(small_grid())[:2]
    exp = tmp_path / "exp"
    runner = FakeLauncher("fail")
    result = run_grid(specs, exp, quiet(), launcher=runner, retries=1, cores=[()])
    assert result.finished == specs and not result.failed and len(runner.calls) == 3
    kept = list((exp / "failures").iterdir())
    assert len(kept) == 1 and (kept[0] / "logs" / "learner.log").read_text() == "boom"

    exp2 = tmp_path / "exp2"
    result = run_grid(specs, exp2, quiet(), launcher=FakeLauncher(*["fail"] * 10), retries=1, fail_fast=True,
                      cores=[()])
    assert result.failed == specs[:1] and result.finished == []
    assert run_state(specs[0], exp2) == "partial"  # redone on the next call


def test_a_run_that_exits_130_stops_the_grid(tmp_path):
    specs = plan(small_grid())
    runner = FakeLauncher("interrupt")
    result = run_grid(specs, tmp_path / "exp", quiet(), launcher=runner, cores=[()])
    assert result.interrupted and len(runner.calls) == 1 and not result.finished and not result.failed


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True)
    return path


# --- one small real grid -------------------------------------------------------------------


@pytest.mark.slow
def test_small_real_grid_in_parallel_then_report_then_resume_from_the_ledger(tmp_path):
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    env = dict(os.environ, COLUMNS="160", PYTHONWARNINGS="ignore")
    args = [sys.executable, "-m", "mam_lab.experiment", "--exp-dir", str(exp), "--envs", "AppleCollect-v0",
            "--algos", "ma-ddpg,ddpg", "--seeds", "2", "--steps", "1500", "--schedule", "equal-data",
            "--hidden", "32,32", "--batch-size", "32",
            "--start-steps", "300", "--compete-every", "300", "--eliminate-at", "900", "--eval-every", "300",
            "--eval-episodes", "2", "--no-plot", "--no-report", "--parallel", "2", "--ledger", str(ledger)]
    first = subprocess.run(args, cwd=ROOT, env=env, text=True, capture_output=True, timeout=600)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "4/4 runs finished (4 now, 0 before), 0 failed" in first.stdout
    assert "2 run(s) at once" in first.stdout
    runs = sorted(exp.glob("AppleCollect-v0/*/seed*/summary.json"))
    assert [p.parent.relative_to(exp).as_posix() for p in runs] == [
        "AppleCollect-v0/ddpg/seed0", "AppleCollect-v0/ddpg/seed1",
        "AppleCollect-v0/ma-ddpg/seed0", "AppleCollect-v0/ma-ddpg/seed1"]
    for p in runs:
        summary = json.loads(p.read_text())
        assert 1500 <= summary["env_steps"] <= 1500 + 5 * 32  # the same budget for both algorithms
        log = (p.parent / "launcher.log").read_text()
        assert "pinned to cores" in log and "done in" in log
        record = json.loads((ledger / p.parent.relative_to(exp) / "record.json").read_text())
        assert record["exit_status"] == 0 and record["parallel"] == 2 and len(record["commit"]) == 40
        assert sum(record["files"].values()) < 300_000
    cfg = {p.parent.parent.name: json.loads((p.parent / "config.json").read_text())["algo"] for p in runs}
    assert (cfg["ma-ddpg"]["actors"], cfg["ma-ddpg"]["workers"], cfg["ddpg"]["actors"]) == (3, 5, 1)
    assert not list(ledger.rglob("*.pt")) and not list(ledger.rglob("*.log"))

    rep = subprocess.run([sys.executable, "-m", "mam_lab.report", str(exp), "--n-boot", "500"], cwd=ROOT, env=env,
                         text=True, capture_output=True, timeout=300)
    assert rep.returncode == 0, rep.stdout + rep.stderr
    text = (exp / "report.md").read_text()
    assert "## AppleCollect-v0" in text and "| ma-ddpg |" in text and "| ddpg |" in text
    assert "P(ma-ddpg > ddpg)" in text and "50 apple" in text
    for name in ("curves_AppleCollect-v0.png", "allocation_AppleCollect-v0.png", "iqm.png"):
        assert (exp / "figures" / name).read_bytes()[:8] == PNG_MAGIC
    assert "ma-ddpg" in rep.stdout and "ddpg" in rep.stdout

    stamps = {p: p.stat().st_mtime_ns for p in runs}
    second = subprocess.run(args, cwd=ROOT, env=env, text=True, capture_output=True, timeout=120)
    assert second.returncode == 0, second.stdout + second.stderr
    assert "4 of 4 runs already finished" in second.stdout and "(0 now, 4 before)" in second.stdout
    assert {p: p.stat().st_mtime_ns for p in runs} == stamps

    # a fresh clone: the experiment directory is gone, the ledger says every run is finished
    fresh = args[:args.index("--exp-dir") + 1] + [str(tmp_path / "fresh")] + args[args.index("--exp-dir") + 2:]
    third = subprocess.run(fresh, cwd=ROOT, env=env, text=True, capture_output=True, timeout=120)
    assert third.returncode == 0, third.stdout + third.stderr
    assert "(0 now, 4 before)" in third.stdout


def write_bias(run_dir: Path, rows: list[tuple[int, int, float]]) -> None:
    """bias.jsonl as the learner writes it: one row per (point, live actor)."""
    with open(run_dir / "bias.jsonl", "w") as f:
        for point, actor, rate in rows:
            f.write(json.dumps({"env_steps": point + 2, "point": point, "updates": point, "bias": {
                "actor": actor, "q_estimate": 1.0, "q_true": 1.0, "bias": 0.0, "bias_rate": rate}}) + "\n")


def test_report_aggregates_the_eq17_bias_rate_over_actors_and_seeds(tmp_path):
    exp = tmp_path / "exp"
    make_experiment(exp)
    ma = exp / "Toy-v0" / "ma-td3"
    # seed 0: point 500 has two live actors (0.2, 0.4) -> 0.3; point 1000 the survivor only: -0.1
    write_bias(ma / "seed0", [(500, 0, 0.2), (500, 1, 0.4), (1000, 1, -0.1)])
    write_bias(ma / "seed1", [(500, 0, 0.5), (500, 1, 0.5), (1000, 1, 0.1)])
    (ma / "seed2" / "bias.jsonl").write_text('{"point": 500, "bias": {"actor": 0, "bias_rate": NaN}}\n')
    write_bias(exp / "Toy-v0" / "td3" / "seed0", [(500, 0, 0.6), (1000, 0, 0.4)])
    with open(exp / "Toy-v0" / "td3" / "seed0" / "bias.jsonl", "a") as f:  # before the first update: left out
        f.write(json.dumps({"point": 200, "updates": 0, "bias": {"actor": 0, "bias_rate": 0.99}}) + "\n")
    report, md, pngs = write_report(exp, n_boot=200)
    ma_b, td3_b = report.bias["Toy-v0"]
    assert (ma_b.variant, ma_b.n, td3_b.variant, td3_b.n) == ("ma-td3", 2, "td3", 1)  # seed2: no finite rate
    np.testing.assert_allclose(ma_b.points, [500, 1000])
    np.testing.assert_allclose(td3_b.points, [500, 1000])  # the point before any update is left out
    np.testing.assert_allclose(ma_b.rates, [[0.3, -0.1], [0.5, 0.1]])
    np.testing.assert_allclose(ma_b.per_run(np.mean), [0.1, 0.3])
    np.testing.assert_allclose(ma_b.per_run(lambda x: np.mean(np.abs(x))), [0.2, 0.3])
    _, rows = bias_rows(report.bias["Toy-v0"])
    assert rows[0][:3] == ["ma-td3", "2", "2"] and rows[0][3].startswith("0.200 ± 0.100")
    assert rows[1][5].startswith("0.400 ± 0.000")
    text = md.read_text()
    assert "Estimation bias (Eq. 17), Toy-v0" in text and "figures/bias_Toy-v0.png" in text
    assert (exp / "figures" / "bias_Toy-v0.png").read_bytes()[:8] == PNG_MAGIC


def test_report_compares_bias_only_at_points_every_run_measured(tmp_path):
    exp = tmp_path / "exp"
    make_experiment(exp)
    write_bias(exp / "Toy-v0" / "ma-td3" / "seed0", [(500, 0, 0.2), (1000, 0, 0.4)])
    write_bias(exp / "Toy-v0" / "td3" / "seed0", [(500, 0, 0.6)])  # no point at 1000
    ma_b, td3_b = build_report(exp, n_boot=100).bias["Toy-v0"]
    np.testing.assert_allclose(ma_b.points, [500])
    np.testing.assert_allclose(ma_b.rates, [[0.2]])
    np.testing.assert_allclose(td3_b.rates, [[0.6]])


# --- parallel runs, affinity, Ctrl-C ---------------------------------------------------------


def test_core_slots_and_default_parallel():
    assert core_slots(2, [0, 1]) == [(0,), (1,)]
    assert core_slots(2, [0, 1, 2, 3, 4]) == [(0, 1), (2, 3)]
    assert core_slots(1, [3, 1]) == [(1, 3)]
    assert core_slots(3, [0, 1]) == [(0,), (1,), (0,)]  # more runs than cores: shared round-robin
    assert default_parallel(1, [0, 1]) == 2 and default_parallel(2, [0, 1, 2, 3, 4]) == 2
    assert default_parallel(4, [0, 1]) == 1
    with pytest.raises(ValueError):
        core_slots(0, [0])


def _timing(exp: Path, spec) -> dict[str, Any]:
    return json.loads((exp / spec.path / "timing.json").read_text())


def test_parallel_runs_go_side_by_side_each_on_its_own_cores(tmp_path):
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    cores = sorted(os.sched_getaffinity(0))
    slots = [(cores[0],), (cores[-1],)]
    runner = FakeLauncher(delay=1.5)
    result = run_grid(specs, exp, quiet(), launcher=runner, parallel=2, cores=slots)
    assert result.finished == specs and not result.failed and not result.interrupted
    times = [_timing(exp, s) for s in specs]
    # two at a time: runs 0 and 1 overlap, and so do 2 and 3; the third starts after one ended
    assert times[0]["start"] < times[1]["end"] and times[1]["start"] < times[0]["end"]
    assert times[2]["start"] >= min(times[0]["end"], times[1]["end"]) - 0.05
    assert result.elapsed_s < 4 * 1.5  # not one after the other
    # every run on the cores of its slot, and the two concurrent runs on different slots
    assert all(tuple(t["cores"]) in slots for t in times)
    assert set(runner.cores[:2]) == set(slots)


def test_ctrl_c_stops_every_run_and_a_rerun_resumes(tmp_path):
    exp = tmp_path / "exp"
    ledger = tmp_path / "ledger"
    script = f"""
import sys
sys.path.insert(0, {str(ROOT)!r})
sys.path.insert(0, {str(Path(__file__).parent)!r})
from pathlib import Path
from test_experiment import FakeLauncher, quiet, small_grid
from mam_lab.grid import plan
from mam_lab.scheduler import run_grid
specs = plan(small_grid())
r = run_grid(specs, Path({str(exp)!r}), quiet(), launcher=FakeLauncher("ok", "hang", "hang"), parallel=2,
             cores=[(), ()], ledger=Path({str(ledger)!r}))
print("RESULT", r.interrupted, len(r.finished), len(r.failed), flush=True)
sys.exit(130 if r.interrupted else 0)
"""
    # Ctrl-C as a shell delivers it: the default disposition, whatever this process inherited
    # (an ignored SIGINT survives exec, and Python then never raises KeyboardInterrupt)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    specs = plan(small_grid())
    deadline = time.monotonic() + 60
    # run 0 finishes at once, then runs 1 and 2 hang side by side
    while time.monotonic() < deadline and not all(
            "hanging" in _read(exp / s.path / "launcher.log") for s in specs[1:3]):
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out
    assert "RESULT True 1 0" in out  # interrupted, run 0 finished, none failed
    assert run_state(specs[0], exp, ledger) == "done"
    assert [run_state(s, exp) for s in specs[1:]] == ["partial", "partial", "todo"]
    # the hanging runs got SIGTERM and exited: no process of theirs is left
    leftover = subprocess.run(["pgrep", "-f", str(exp)], capture_output=True, text=True)
    assert leftover.stdout.strip() == ""
    # a rerun redoes the partial runs and skips the finished one
    runner = FakeLauncher()
    result = run_grid(specs, exp, quiet(), launcher=runner, parallel=2, cores=[(), ()], ledger=ledger)
    assert result.skipped == specs[:1] and result.finished == specs[1:]
    assert sorted(runner.calls) == sorted(exp / s.path for s in specs[1:])


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except FileNotFoundError:
        return ""


def test_experiment_run_exit_status_and_pinning(tmp_path):
    """The real run process: pinned to the cores it is given; a run that cannot start exits 1."""
    run_dir = _mkdir(tmp_path / "run")
    core = sorted(os.sched_getaffinity(0))[-1]
    cfg = plan(small_grid())[0].run_config("x").to_dict()
    cfg["algo"]["batch_size"] = 0  # invalid: RunConfig.from_dict refuses it
    write_json(run_dir / "launch.json", {"config": cfg, "cores": [core], "plot": False})
    out = subprocess.run([sys.executable, "-m", "mam_lab.experiment_run", str(run_dir)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stdout + out.stderr
    assert f"pinned to cores [{core}]" in out.stdout and "Traceback" in out.stderr


# --- the ledger ------------------------------------------------------------------------------


def test_thin_indices_keep_first_last_and_even_spacing():
    assert thin_indices(5, 300) == [0, 1, 2, 3, 4]
    assert thin_indices(0, 300) == []
    assert thin_indices(11, 3) == [0, 5, 10]
    idx = thin_indices(10_000, 300)
    assert len(idx) == 300 and idx[0] == 0 and idx[-1] == 9999
    gaps = np.diff(idx)
    assert gaps.min() >= 33 and gaps.max() <= 34


def test_thin_jsonl_skips_corrupt_lines(tmp_path):
    src = tmp_path / "a.jsonl"
    src.write_text("".join(json.dumps({"i": i}) + "\n" for i in range(1000)) + "not json\n[1]\n")
    kept, total = thin_jsonl(src, tmp_path / "b.jsonl", 100)
    rows = [json.loads(line) for line in (tmp_path / "b.jsonl").read_text().splitlines()]
    assert (kept, total) == (100, 1000) and len(rows) == 100
    assert rows[0] == {"i": 0} and rows[-1] == {"i": 999}


def test_finished_runs_go_to_the_ledger_and_a_fresh_clone_resumes_from_it(tmp_path):
    specs = plan(small_grid())
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    result = run_grid(specs[:2], exp, quiet(), launcher=FakeLauncher(), cores=[()], ledger=ledger,
                      experiment="toy")
    assert result.finished == specs[:2]
    for spec in specs[:2]:
        rec_dir = ledger / spec.path
        names = {p.name for p in rec_dir.iterdir()}
        assert names == {"config.json", "summary.json", "eval.jsonl", "learner.jsonl", "record.json"}
        rows = (rec_dir / "learner.jsonl").read_text().splitlines()
        assert len(rows) == LEARNER_ROWS and json.loads(rows[-1])["env_steps"] == 999
        record = json.loads((rec_dir / "record.json").read_text())
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        assert record["commit"] == head and isinstance(record["dirty"], bool)
        assert record["exit_status"] == 0 and record["experiment"] == "toy"
        assert record["spec"]["variant"] == spec.variant and record["spec"]["seed"] == spec.seed
        assert record["learner_rows"] == {"kept": LEARNER_ROWS, "of": 1000}
        assert record["files"]["learner.jsonl"] == (rec_dir / "learner.jsonl").stat().st_size
        assert record["run_wall_s"] > 0 and "torch" in record["versions"]
        assert (exp / spec.path / "record.json").is_file()  # and beside the run
    # a fresh clone: no experiment directory, only the ledger
    fresh = tmp_path / "fresh"
    assert [run_state(s, fresh, ledger) for s in specs] == ["done", "done", "todo", "todo"]
    check_resume(specs, fresh, ledger)
    runner = FakeLauncher()
    result = run_grid(specs, fresh, quiet(), launcher=runner, cores=[()], ledger=ledger)
    assert result.skipped == specs[:2] and result.finished == specs[2:]
    assert runner.calls == [fresh / s.path for s in specs[2:]]
    assert all(in_ledger(s, ledger) for s in specs)
    # the config check applies to ledger records too
    other = plan(make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds="2", steps=600,
                           flags={"hidden": "8,8", "batch_size": 8}))
    with pytest.raises(GridError, match="different grid"):
        check_resume(other, tmp_path / "another", ledger)


def test_runs_finished_before_the_ledger_are_copied_to_it(tmp_path):
    specs = plan(small_grid())[:1]
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    finish_fake(specs[0], exp)
    result = run_grid(specs, exp, quiet(), launcher=FakeLauncher(), cores=[()], ledger=ledger)
    assert result.skipped == specs
    record = json.loads((ledger / specs[0].path / "record.json").read_text())
    assert record["backfilled"] is True and record["commit"]


# --- named variants ----------------------------------------------------------------------------


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


# --- verdict, 50 apple, x-axis, reports from the ledger ----------------------------------------


def test_verdict_words():
    # the CI of P(MA > baseline) and the Holm-adjusted exact p (tests/test_verdict.py has the rest)
    assert verdict_word(Interval(0.8, 0.55, 0.95), 5, 5, 0.01, 0.99) == "better"
    assert verdict_word(Interval(0.2, 0.05, 0.45), 5, 5, 0.99, 0.01) == "worse"
    assert verdict_word(Interval(0.6, 0.5, 0.9), 5, 5, 0.01, 0.99) == "not separated"  # the bound must be above 0.5
    assert verdict_word(Interval(0.4, 0.1, 0.5), 5, 5, 0.99, 0.01) == "not separated"
    assert verdict_word(Interval(0.5, 0.2, 0.8), 5, 5, 0.5, 0.5) == "not separated"
    assert verdict_word(Interval(1.0, 1.0, 1.0), 1, 2, 0.0, 1.0) == "too few runs"  # one run: a degenerate CI
    assert verdict_word(Interval(1.0, 1.0, 1.0), 3, 3, 0.05, 1.0) == "too few runs"  # 3 vs 3: least p is 1/20
    assert verdict_word(Interval(math.nan, math.nan, math.nan), 5, 5, math.nan, math.nan) == "not separated"


def test_wilson_interval_more_hand_computed_values():
    # p̂ = 2/3, z = 1.96: centre (p̂ + z²/2n)/(1 + z²/n) = 0.5731, half-width 0.3654
    w = wilson_interval(2, 3)
    assert (w.lo, w.hi) == (pytest.approx(0.2077, abs=1e-3), pytest.approx(0.9385, abs=1e-3))
    w = wilson_interval(1, 20)  # published: (0.0089, 0.2361)
    assert (w.lo, w.hi) == (pytest.approx(0.0089, abs=1e-3), pytest.approx(0.2361, abs=1e-3))


def test_fifty_apple_bound_and_first_reach():
    # a 50 apple reached at the last of the 100 steps: 50 − 100·0.01 = 49; the best 10 apple: 9.99
    assert 48.99 < SUCCESS_RETURN <= 49.0 and 50 + 100 * -0.01 >= SUCCESS_RETURN
    triples = [(100, 33.0, 9.97), (200, 66.0, 49.96), (300, None, 9.97), (400, 133.0, 49.9)]
    assert first_reach(triples, SUCCESS_RETURN) == (200, 66.0)
    assert first_reach(triples[:1], SUCCESS_RETURN) is None


def _set_record(run_dir: Path, commit: str, dirty: bool = False) -> None:
    write_json(run_dir / "record.json", {"commit": commit, "dirty": dirty})


def test_verdict_table_on_constructed_runs(tmp_path):
    exp = tmp_path / "exp"
    env = exp / "Toy-v0"
    for seed in range(5):
        write_run(env / "ma-td3" / f"seed{seed}", "ma-td3", seed, 2, lambda s, sd=seed: s / 100 + sd)  # above TD3
        write_run(env / "ma-td3-slow" / f"seed{seed}", "ma-td3", seed, 2, lambda s, sd=seed: s / 400 + 0.1 * sd)
        write_run(env / "ma-td3-same" / f"seed{seed}", "ma-td3", seed, 2, lambda s, sd=seed: s / 200 + sd - 1.5)
        write_run(env / "td3" / f"seed{seed}", "td3", seed, 1, lambda s, sd=seed: s / 200 + sd - 1.5)
        for v in ("ma-td3", "ma-td3-slow", "ma-td3-same", "td3"):
            _set_record(env / v / f"seed{seed}", "a" * 40)
    _set_record(env / "td3" / "seed4", "b" * 40, dirty=True)  # one baseline run at another commit
    planned = [f"Toy-v0/{v}/seed{s}" for s in range(6) for v in ("ma-td3", "ma-td3-slow", "ma-td3-same", "td3")]
    write_json(exp / "experiment.json", {"name": "toy", "runs": [
        {"path": p, "env": "Toy-v0", "variant": p.split("/")[1], "algo": "td3" if "/td3/" in p else "ma-td3",
         "flags": {}} for p in planned]})
    report, md, _ = write_report(exp, n_boot=500, figures=False)
    by = {v.variant: v for v in report.verdicts}
    assert set(by) == {"ma-td3", "ma-td3-slow", "ma-td3-same"}
    assert all(v.baseline == "td3" and v.env == "Toy-v0" and (v.n_x, v.n_y) == (5, 5) for v in by.values())
    # the deployed actor's final return: the mean of the last 3 grid points 1800, 1900, 2000 (the best
    # actor survived): ma-td3 (18 + 19 + 20)/3 + seed = 19 + seed; td3 (9 + 9.5 + 10)/3 + seed − 1.5 = 8 + seed
    np.testing.assert_allclose(by["ma-td3"].final_x, [19, 20, 21, 22, 23])
    np.testing.assert_allclose(by["ma-td3"].final_y, [8, 9, 10, 11, 12])
    np.testing.assert_allclose(by["ma-td3-slow"].final_x, 4.75 + 0.1 * np.arange(5))
    # complete separation 5 vs 5: raw exact p 1/252, Holm over the 3 rows sharing TD3: 3/252 < 0.05
    assert by["ma-td3"].final.test.p_greater == pytest.approx(1 / 252)
    assert by["ma-td3"].final.test.p_greater_holm == pytest.approx(3 / 252)
    assert by["ma-td3"].p.value == 1.0 and by["ma-td3"].word == "better" and by["ma-td3"].final.stable
    assert by["ma-td3-slow"].p.value == 0.0 and by["ma-td3-slow"].word == "worse"
    assert by["ma-td3-same"].p.value == 0.5 and by["ma-td3-same"].word == "not separated"
    assert by["ma-td3"].iqm_x.value == pytest.approx(iqm([15.5, 16.5, 17.5, 18.5, 19.5]))  # best-of-K last-10
    assert by["ma-td3"].wall_x == pytest.approx(np.mean([20, 21, 22, 23, 24]))  # launcher wall time per run
    assert by["ma-td3"].commits == {"a" * 12: 9, "b" * 12 + "+modified": 1} and by["ma-td3"].mixed
    assert any("td3: runs at different commits" in n and "bbbbbbbbbbbb+modified (1)" in n for n in report.notes)
    # 6 seeds planned, 5 finished: the row says how many of its runs are in the ledger
    assert not by["ma-td3"].complete and (by["ma-td3"].planned_x, by["ma-td3"].planned_y) == (6, 6)
    text = md.read_text()
    assert text.index("## Verdict") < text.index("## Toy-v0")
    assert "| Toy-v0 | ma-td3 | td3 | 5 / 5 (10 of 12 runs in the ledger) |" in text
    assert "| 1.00 [1.00, 1.00] | 0.004 / 0.012 |" in text and "same for 20/20 seeds | *better* |" in text
    assert "*worse*" in text and "*not separated*" in text and "**different commits**" in text
    assert "Tables on the x-axis: **env transitions" in text


def test_report_of_a_grid_not_started_says_how_many_runs_are_in_the_ledger(tmp_path):
    grid = tmp_path / "g.toml"
    env = "AppleCollect-v1"
    grid.write_text(f'name = "g"\nenvs = ["{env}"]\nsteps = 2000\n[env-seeds]\n"{env}" = 5\n'
                    '[variant.td3]\nalgo = "td3"\n[variant.ma-td3]\nalgo = "ma-td3"\n')
    report, md, _ = write_report(tmp_path / "nothing-yet", n_boot=200, figures=False, grid_file=grid)
    assert not report.verdicts and len(report.pending) == 1
    (row,) = report.pending
    assert (row.variant, row.baseline, row.have, row.planned) == ("ma-td3", "td3", 0, 10)
    assert row.text() == "0 of 10 runs in the ledger (ma-td3 0/5, td3 0/5)"
    assert f"| {env} | ma-td3 | td3 | 0 of 10 runs in the ledger (ma-td3 0/5, td3 0/5) |" in md.read_text()
    assert "*not yet run*" in md.read_text()
    # two runs finished: still pending, with its count
    for seed in range(2):
        for algo, k in (("ma-td3", 2), ("td3", 1)):
            d = tmp_path / "some" / env / algo / f"seed{seed}"
            write_run(d, algo, seed, k, lambda s: s / 100)
            cfg = json.loads((d / "config.json").read_text())
            (d / "config.json").write_text(json.dumps({**cfg, "env_id": env}))
    report, md, _ = write_report(tmp_path / "some", n_boot=200, figures=False, grid_file=grid)
    assert report.pending[0].text() == "4 of 10 runs in the ledger (ma-td3 2/5, td3 2/5)"
    assert report.verdicts[0].word == "too few runs"
    assert "| 2 / 2 (4 of 10 runs in the ledger) |" in md.read_text()


def test_iterations_axis_and_curves_on_both_axes(tmp_path):
    exp = tmp_path / "exp"
    for seed in range(2):
        for algo, k in (("ma-td3", 2), ("td3", 1)):
            d = exp / "Toy-v0" / algo / f"seed{seed}"
            write_run(d, algo, seed, k, lambda s: s / 100)
            if algo == "ma-td3" or seed == 0:  # td3 seed 1: an older run without iterations
                rows = [json.loads(line) for line in (d / "eval.jsonl").read_text().splitlines()]
                per = 3 if k > 1 else 1  # MA: 3 slots step together, 3 transitions per iteration
                (d / "eval.jsonl").write_text("".join(json.dumps({**r, "iterations": r["env_steps"] // per}) + "\n"
                                                      for r in rows))
    rep = build_report(exp, n_boot=200, axis="iterations")
    assert rep.axis == "iterations" and rep.axes == ("transitions", "iterations")
    ma, td3 = rep.envs["Toy-v0"]
    assert ma.spacing == pytest.approx(SPACING)  # the largest: TD3's 100 per 100 transitions
    assert ma.grid.max() == pytest.approx(600) and td3.grid.max() == pytest.approx(STEPS)
    assert set(ma.curves_by_axis) == {"transitions", "iterations"}
    assert ma.curves_by_axis["transitions"][0].max() == STEPS
    assert any("1 run(s) without `iterations`" in n for n in rep.notes)
    _, md, pngs = write_report(exp, n_boot=200, axis="iterations")
    assert {p.name for p in pngs} >= {"curves_Toy-v0.png", "curves_Toy-v0_iterations.png"}
    assert "Tables on the x-axis: **iterations" in md.read_text()
    with pytest.raises(ValueError):
        build_report(exp, axis="updates")


def test_report_from_the_ledger_alone_and_from_a_fresh_clone(tmp_path):
    grid = small_grid()
    specs = plan(grid)
    exp, ledger = tmp_path / "exp", tmp_path / "docs" / "results" / "toy" / "runs"
    write_manifest(exp, grid, specs, {}, ledger)
    run_grid(specs[:3], exp, quiet(), launcher=FakeLauncher(), cores=[()], ledger=ledger)
    assert json.loads((ledger / "experiment.json").read_text())["runs"][3]["path"] == specs[3].path.as_posix()
    from_exp = build_report(exp, n_boot=200)
    shutil.rmtree(exp)  # a fresh clone has only the ledger
    for root in (ledger, ledger.parent):  # the ledger, or docs/results/<exp> holding it in runs/
        rep = build_report(root, n_boot=200)
        assert {(v.variant, v.n) for v in rep.envs["AppleCollect-v0"]} == {("ma-ddpg", 2), ("ddpg", 1)}
        assert rep.missing == [specs[3].path.as_posix()]
        assert all(r.commit != "unknown" for v in rep.envs["AppleCollect-v0"] for r in v.runs)
    assert {(v.variant, v.n) for v in from_exp.envs["AppleCollect-v0"]} == {("ma-ddpg", 2), ("ddpg", 1)}
    _, md, _ = write_report(ledger.parent, n_boot=200, figures=False)
    assert md == ledger.parent / "report.md" and "| ma-ddpg |" in md.read_text()
    # an experiment directory whose runs are only in its ledger
    write_manifest(tmp_path / "again", grid, specs, {}, ledger)
    rep = build_report(tmp_path / "again", n_boot=200)
    assert sum(v.n for v in rep.envs["AppleCollect-v0"]) == 3


def test_ledger_compacts_repeated_allocation_rows(tmp_path):
    from mam_lab.ledger import compact_allocation

    def row(reason, round_, slots, survivor=None, t=0.0):
        return json.dumps({"t": t, "round": round_, "probabilities": [0.5, 0.5], "slots": slots,
                           "eliminated": [False, False], "survivor": survivor, "reason": reason})

    src, dest = tmp_path / "allocation.jsonl", tmp_path / "out.jsonl"
    src.write_text("\n".join([
        row("initial", 0, {"w0": 0}), row("workers-changed", 0, {"w0": 0, "w1": 1}),
        row("workers-changed", 0, {"w0": 0, "w1": 1}, t=1.0),  # a repeat: dropped
        row("round", 1, {"w0": 1, "w1": 1}), row("round", 1, {"w0": 1, "w1": 1}, t=2.0),  # rounds always kept
        row("workers-changed", 1, {"w0": 1}), "not json", ""]) + "\n")
    assert compact_allocation(src, dest) == (5, 7)
    kept = [json.loads(line) for line in dest.read_text().splitlines()]
    assert [r["reason"] for r in kept] == ["initial", "workers-changed", "round", "round", "workers-changed"]


def test_only_the_learner_of_a_parallel_run_is_pinned(monkeypatch):
    """`mam experiment --parallel`: the run's cores go to its learner; referee and workers float."""
    from services.run.launcher import LEARNER_CPUS_ENV, _child_setup

    every = sorted(os.sched_getaffinity(0))
    monkeypatch.setenv(LEARNER_CPUS_ENV, str(every[0]))
    code = [sys.executable, "-c", "import os; print(sorted(os.sched_getaffinity(0)))"]
    learner = subprocess.run(code, preexec_fn=_child_setup("learner"), capture_output=True, text=True, check=True)
    worker = subprocess.run(code, preexec_fn=_child_setup("worker-0"), capture_output=True, text=True, check=True)
    assert json.loads(learner.stdout) == [every[0]]
    assert json.loads(worker.stdout) == every
