"""`mam report` (mam_lab/report.py, analysis.py, tables.py): statistics, files and verdicts of an experiment."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from mam_lab.analysis import build_report
from mam_lab.grid import plan
from mam_lab.ledger import (
    write_manifest,
)
from mam_lab.report import write_report
from mam_lab.scheduler import run_grid
from mam_lab.stats import (
    iqm,
)
from mam_lab.tables import bias_rows
from services.run.rundir import write_json
from tests.lab_fixtures import (
    PNG_MAGIC,
    SPACING,
    STEPS,
    FakeLauncher,
    _set_record,
    make_experiment,
    quiet,
    small_grid,
    write_bias,
    write_run,
)


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



def test_training_returns_are_drawn_from_whole_logs_and_ledger_files_never_from_thinned_ones(tmp_path):
    exp = tmp_path / "exp"
    make_experiment(exp)
    runs = {s: exp / "Toy-v0" / "ma-td3" / f"seed{s}" for s in (0, 1, 2)}
    whole = [{"env_steps": x, "iterations": x, "train_return": x / 10} for x in range(100, STEPS + 1, 100)]
    # seed 0: a run directory with its whole learner.jsonl (rows without a training return in between)
    (runs[0] / "learner.jsonl").write_text("".join(json.dumps(r) + "\n" + json.dumps({"iterations": r["iterations"]
                                                                                     + 50}) + "\n" for r in whole))
    # seed 1: a ledger record with train_returns.jsonl; seed 2: an older record, learner.jsonl thinned
    (runs[1] / "train_returns.jsonl").write_text("".join(json.dumps({**r, "train_return": -1.0}) + "\n"
                                                        for r in whole))
    (runs[2] / "learner.jsonl").write_text(json.dumps(whole[3]) + "\n")
    write_json(runs[2] / "record.json", {"commit": "abc", "learner_rows": {"kept": 200, "of": 5000}})
    report, md, pngs = write_report(exp, n_boot=200)
    ma = {r.seed: r for v in report.envs["Toy-v0"] if v.variant == "ma-td3" for r in v.runs}
    assert ma[0].train == [(float(x), x / 10) for x in range(100, STEPS + 1, 100)]
    assert ma[1].train == [(float(x), -1.0) for x in range(100, STEPS + 1, 100)]
    assert ma[2].train == []
    assert all(not r.train for v in report.envs["Toy-v0"] if v.variant == "td3" for r in v.runs)
    png = exp / "figures" / "training_Toy-v0.png"
    assert png in pngs and png.read_bytes()[:8] == PNG_MAGIC and "figures/training_Toy-v0.png" in md.read_text()
    for p in runs.values():  # no training returns anywhere: no figure
        for name in ("learner.jsonl", "train_returns.jsonl"):
            (p / name).unlink(missing_ok=True)
    _, _, pngs = write_report(exp, n_boot=200)
    assert not any(p.name.startswith("training_") for p in pngs)
