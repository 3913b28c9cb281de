"""`mam run`'s progress view is a pure function of what is known of the run (issue 39, item 4):
progress.py takes the run's config and `mam watch`'s MonitorState, fed real messages, and returns
text; it imports neither the launcher nor the cluster of child processes, nor a clock or the bus."""

from __future__ import annotations

import ast

from mam_core.config import resolve
from services.messaging.codec import Allocation, Eval, LearnerStats
from services.roles.monitor_view import MonitorState, message_body
from services.run.config import RunConfig
from services.run.progress import allocation_line, bar_info, done_text, outcome_text
from tests.test_layers import ROOT, imports, modules

CFG = RunConfig(run="view", env_id="AppleCollect-v1", steps=400, algo=resolve("ma-ddpg", actors=3, workers=5))


def test_the_progress_view_imports_no_supervision_no_clock_and_no_bus():
    taken = imports("services.run.progress", ROOT / "services" / "run" / "progress.py", modules())
    assert not {"services.run.launcher", "services.run.cluster", "services.run.errors",
                "services.messaging.bus"} & set(taken), sorted(taken)
    tree = ast.parse((ROOT / "services" / "run" / "progress.py").read_text())
    outside = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    outside |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert not {"time", "zenoh", "subprocess", "signal"} & outside, sorted(outside)


def test_the_bar_shows_what_the_monitor_state_knows():
    clock = [100.0]
    state = MonitorState(run=CFG.run, env_id=CFG.env_id, algo=CFG.algo.algo, steps=CFG.steps, now=lambda: clock[0])
    state.on_config(CFG.to_dict() | {"algo": CFG.algo.algo, "algo_config": CFG.algo.to_dict()})
    state.on_stats(message_body(LearnerStats(env_steps=1000, updates=50, accept_until=1200, utd=1.0)))
    assert bar_info(CFG, state) == "it 200/400 upd 50  "  # no rates before two stats, no evaluation yet
    clock[0] += 2.0
    state.on_stats(message_body(LearnerStats(env_steps=1200, updates=90, accept_until=1400, utd=1.0)))
    state.on_eval(message_body(Eval(round=1, env_steps=1200, returns=((1.0,), (2.5,), ()), mean=(1.0, 2.5, None),
                                    versions=(3, 3, 3))))
    assert bar_info(CFG, state) == "it 240/400 upd 90 100 transitions/s 20 upd/s  R=[1.00 2.50 —]"
    state.on_stats(message_body(LearnerStats(env_steps=2000, updates=400, accept_until=2000, utd=1.0, done=True)))
    assert bar_info(CFG, state) == "it 400/400 upd 400  budget reached: final evaluation"


def test_an_allocation_line_and_the_done_line_from_plain_data():
    alloc = Allocation(round=2, env_steps=1200, returns=(1.0, 2.5, 2.5), probabilities=(0.2, 0.4, 0.4),
                       counts=(1, 2, 2), slots={}, eliminated=(False,) * 3, survivor=None, reason="competition")
    assert allocation_line(CFG, alloc) == ("[magenta]competition[/] at iteration 240 (1,200 transitions): round 2  "
                                           "R=[1.00 2.50 2.50]  P=[0.20 0.40 0.40]  I=[1 2 2]")
    summary = {"launcher_wall_time_s": 70.4, "final_returns": [1.0, 49.94, None], "survivor": 1}
    assert done_text(CFG, summary, 61.0) == ("[bold green]done[/] in 70 s (budget reached at 0:01:01, then the final "
                                             "evaluation): final returns [1.00, 49.94, —], survivor 1")
    assert outcome_text(CFG, summary) == "survivor 1 reaches the 50 apple in 6 steps: 49.94 of 49.94 possible"
