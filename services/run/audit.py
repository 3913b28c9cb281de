"""What the workers sent against what the replay holds, per worker incarnation (`mam run` and `mam chaos`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from services.run import rundir
from services.run.rundir import write_json


def audit_transport(run_dir: Path) -> dict[str, Any]:
    """Every row a worker sent against the rows the learner counted into its replay, per
    worker incarnation and over all learner incarnations; written into transport.json (`audit`).

    Sent rows come from `workers/<id>-<incarnation>.batches` (one line per batch, written
    before the batch is put, so a killed worker's log holds everything it sent); rows in the
    replay from transport.json's `rows_per_stream` (carried over learner restarts through the
    checkpoints), and `skipped_per_stream`: rows received for iterations the slot already had
    (a worker that took its slot over behind the learner, its predecessor's late batches).
    `lost_rows`: sent and neither in the replay nor skipped; `duplicated_rows`: in the replay
    (or skipped) more often than sent. Empty if the run has no transport.json.
    """
    path = run_dir / rundir.TRANSPORT
    if not path.is_file():
        return {}
    transport = json.loads(path.read_text())
    in_replay: dict[str, int] = {k: int(v) for k, v in transport.get("rows_per_stream", {}).items()}
    skipped: dict[str, int] = {k: int(v) for k, v in transport.get("skipped_per_stream", {}).items()}
    sent: dict[str, int] = {}
    for log_path in sorted((run_dir / rundir.WORKERS).glob("*.batches")):
        worker, _, incarnation = log_path.stem.rpartition("-")
        seen: dict[int, int] = {}
        for line in log_path.read_text(errors="replace").splitlines():
            parts = line.split()
            if len(parts) == 2 and parts[0].isdigit() and parts[1].isdigit():
                seen.setdefault(int(parts[0]), int(parts[1]))
        sent[f"{worker}/{incarnation}"] = sum(seen.values())
    per_stream = {s: {"sent": sent.get(s, 0), "in_replay": in_replay.get(s, 0), "skipped": skipped.get(s, 0)}
                  for s in sorted(set(sent) | set(in_replay))}
    audit = {
        "sent_rows": sum(sent.values()), "replay_rows": sum(in_replay.values()), "skipped_rows": sum(skipped.values()),
        "lost_rows": sum(max(d["sent"] - d["in_replay"] - d["skipped"], 0) for d in per_stream.values()),
        "duplicated_rows": sum(max(d["in_replay"] + d["skipped"] - d["sent"], 0) for d in per_stream.values()),
        "streams": len(per_stream), "streams_without_log": sorted(s for s in in_replay if s not in sent),
        "per_stream": per_stream,
    }
    transport["audit"] = audit
    write_json(path, transport)
    return audit
