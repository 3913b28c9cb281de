"""TensorBoard event files of a run: RUN_DIR/tb/<role>/ (learner, referee).

`tensorboard --logdir runs` then shows every run side by side (each run as NAME/tb/learner and
NAME/tb/referee: one event file per writing process, so no reader has to merge two files that
grow at once). The JSONL files stay the source of truth: each role writes every JSONL row
first and then the same numbers, picked by the `*_scalars` functions below, as TensorBoard
scalars. The x-axis (step) is env transitions received by the learner (`env_steps`).

Tags:
- learner (learner.jsonl, every second): loss/critic, loss/actor (summed over the actors),
  loss/actor{k}, q/actor{k} (mean Q of actor k's critics on the last batch), for SAC loss/alpha
  and alpha/actor{k} (the temperatures), learner/updates_per_s, learner/transitions_per_s,
  learner/utd, learner/replay_size, learner/updates, learner/iterations (when the row has it),
  learner/train_return (mean return of the episodes workers finished);
- Eq. 17 bias (bias.jsonl, with --bias-every): bias/rate/actor{k}, bias/q_estimate/actor{k},
  bias/q_true/actor{k};
- referee (eval.jsonl): eval/return/actor{k} (mean of the deterministic evaluation), and
  eval/return_std/actor{k};
- referee (allocation.jsonl): allocation/P/actor{k} (Eq. 8), allocation/I/actor{k} (slots
  running actor k), allocation/round, allocation/survivor (-1 until the elimination),
  allocation/eliminated/actor{k} (0 or 1).

The writer is the `tensorboard` package's own event-file writer (what torch.utils.tensorboard
uses underneath), imported on first use: it does not import torch, so the referee stays
torch-free. A writer that fails logs once and stops; training never depends on it.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from services.run import rundir

log = logging.getLogger("mam.tb")

TB_DIR = rundir.TB
FLUSH_SECS = 5.0  # events reach the file at least this often (and at close)

Row = Mapping[str, Any]
Scalars = dict[str, float]


def _put(out: Scalars, tag: str, value: Any) -> None:
    if isinstance(value, bool):
        value = float(value)
    if isinstance(value, (int, float)) and math.isfinite(value):
        out[tag] = float(value)


def learner_scalars(row: Row) -> Scalars:
    out: Scalars = {}
    for key, value in row.items():
        if key.startswith(("loss/", "q/", "alpha/")):  # alpha/actor{k}: SAC's temperatures
            _put(out, key, value)
    for key, tag in (("updates_per_s", "learner/updates_per_s"), ("transitions_per_s", "learner/transitions_per_s"),
                     ("utd", "learner/utd"), ("buffer", "learner/replay_size"), ("updates", "learner/updates"),
                     ("iterations", "learner/iterations"), ("train_return", "learner/train_return")):
        _put(out, tag, row.get(key))
    return out


def bias_scalars(row: Row) -> Scalars:
    out: Scalars = {}
    b = row.get("bias") or {}
    k = b.get("actor")
    if isinstance(k, int):
        for key in ("rate", "q_estimate", "q_true"):
            _put(out, f"bias/{key}/actor{k}", b.get("bias_rate" if key == "rate" else key))
    return out


def eval_scalars(row: Row) -> Scalars:
    out: Scalars = {}
    for k, (mean, returns) in enumerate(zip(row.get("mean") or [], row.get("returns") or [])):
        if mean is not None:
            _put(out, f"eval/return/actor{k}", mean)
            if returns:
                m = sum(returns) / len(returns)
                _put(out, f"eval/return_std/actor{k}", math.sqrt(sum((r - m) ** 2 for r in returns) / len(returns)))
    return out


def allocation_scalars(row: Row) -> Scalars:
    out: Scalars = {}
    for k, p in enumerate(row.get("probabilities") or []):
        _put(out, f"allocation/P/actor{k}", p)
    for k, n in enumerate(row.get("counts") or []):
        _put(out, f"allocation/I/actor{k}", n)
    for k, e in enumerate(row.get("eliminated") or []):
        _put(out, f"allocation/eliminated/actor{k}", bool(e))
    _put(out, "allocation/round", row.get("round"))
    survivor = row.get("survivor")
    _put(out, "allocation/survivor", -1 if survivor is None else survivor)
    return out


class RunBoard:
    """One event file under RUN_DIR/tb/<role>/ for one process."""

    def __init__(self, run_dir: Path, role: str, flush_secs: float = FLUSH_SECS) -> None:
        self.logdir = Path(run_dir) / TB_DIR / role
        self._writer: Any = None
        self._event: Any = None
        try:
            from tensorboard.compat.proto.event_pb2 import Event
            from tensorboard.summary.writer.event_file_writer import EventFileWriter

            self.logdir.mkdir(parents=True, exist_ok=True)
            self._writer = EventFileWriter(str(self.logdir), flush_secs=flush_secs)
            self._event = Event
        except Exception as e:  # no tensorboard installed, or an unwritable directory
            log.warning("no TensorBoard event files for this %s (%s: %s); the JSONL logs are complete",
                        role, type(e).__name__, e)

    @property
    def enabled(self) -> bool:
        return self._writer is not None

    def scalars(self, step: int, values: Mapping[str, float], wall_time: float | None = None) -> None:
        if self._writer is None or not values:
            return
        try:
            event = self._event(wall_time=time.time() if wall_time is None else wall_time, step=int(step))
            for tag, value in values.items():
                event.summary.value.add(tag=tag, simple_value=float(value))
            self._writer.add_event(event)
        except Exception:
            log.exception("TensorBoard writing failed; no more event files from this process")
            self._disable()

    def row(self, row: Row, to_scalars: Callable[[Row], Scalars]) -> None:
        """A JSONL row's scalars at its env_steps."""
        step = row.get("env_steps")
        if isinstance(step, int):
            self.scalars(step, to_scalars(row))

    def tee(self, jsonl: Any, to_scalars: Callable[[Row], Scalars]) -> "Tee":
        return Tee(jsonl, self, to_scalars)

    def flush(self) -> None:
        if self._writer is not None:
            try:
                self._writer.flush()
            except Exception:
                self._disable()

    def _disable(self) -> None:
        writer, self._writer = self._writer, None
        try:
            writer.close()
        except Exception:
            pass

    def close(self) -> None:
        if self._writer is not None:
            self._disable()


class Tee:
    """A JsonlWriter that also sends each row's scalars to a RunBoard (JSONL first)."""

    def __init__(self, jsonl: Any, board: RunBoard, to_scalars: Callable[[Row], Scalars]) -> None:
        self.jsonl, self.board, self.to_scalars = jsonl, board, to_scalars

    def write(self, row: dict[str, Any]) -> None:
        self.jsonl.write(row)
        self.board.row(row, self.to_scalars)

    def close(self) -> None:
        self.jsonl.close()
