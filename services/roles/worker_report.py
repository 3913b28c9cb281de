"""What a worker reports (services/roles/worker.py): its counters on its role-stats topic, and
its file in the run directory."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from services.run import rundir
from services.run.rundir import write_json


class WorkerReports:
    """The reports of a worker (a mixin: it holds the counters named below)."""

    run_dir: Path | None
    report: Any
    id: str
    incarnation: str
    sent_rows: int
    batch_seq: int
    actor: int
    slot: int
    rejects: Any
    waits: str
    weights_held_max: int
    weights_received: int
    weights: Any
    faults: dict[str, int]
    env_remade: int
    kept: Any

    def publish_report(self, force: bool = False) -> None:
        """This worker's counters on mam/<run>/stats/worker-<id> (rejections are visible there)."""
        self.report.publish({"incarnation": self.incarnation, "sent_rows": self.sent_rows, "batches": self.batch_seq,
                             "actor": self.actor, "slot": self.slot, "rejected": self.rejects.counts(),
                             "waits": self.waits,
                             **self.fault_counters()}, seq=self.batch_seq, force=force)

    def write_report(self) -> None:
        """What this incarnation sent (compared with the learner's transport.json in tests)."""
        if self.run_dir is None:
            return
        write_json(self.run_dir / rundir.WORKERS / f"{self.id}-{self.incarnation}.json", {
            "worker": self.id, "incarnation": self.incarnation, "sent_rows": self.sent_rows,
            "batches": self.batch_seq, "rejected": self.rejects.counts(), "weights_held_max": self.weights_held_max,
            "weights_received": self.weights_received + (0 if self.weights.closed else self.weights.received),
            **self.fault_counters()})

    def fault_counters(self) -> dict[str, Any]:
        """Simulator faults and resends (role_stats topic and workers/*.json)."""
        return {"env_faults": dict(self.faults), "env_remade": self.env_remade, **self.kept.counters()}
