"""The lab: measuring and comparing runs of the distributed system, apart from the processes that
run in production (`services/`) and the pure algorithm (`mam_core/`).

    experiment.py   `mam experiment`: the command. grid.py (which runs), ledger.py (records of
                    finished runs, resuming), scheduler.py (P runs at once, one process each),
                    view.py (progress), experiment_run.py (one run: `python -m mam_lab.experiment_run`)
    report.py       `mam report`: the command. runs.py (reading run directories), scores.py (per-run
                    scores), stats.py (IQM, bootstrap CIs, P(X > Y), Wilson, the verdict word),
                    analysis.py (the statistics of an experiment), tables.py, figures.py
    bench.py        `mam bench`: the command. bench_sizes.py, bench_learner.py, bench_runs.py,
                    bench_transport.py, bench_lag.py (the pieces)
    provenance.py   the commit and library versions behind a result

The lab imports services (it starts runs, reads their files); no module under services/ imports the
lab, except `mam`'s command registration (services/cli/app.py), lazily.
"""

import mam_core  # noqa: F401, E402  (first: pins the arithmetic before numpy or torch load, mam_core/arithmetic.py)
