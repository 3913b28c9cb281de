"""Which code a run ran (RUN_DIR/code.json), and whether a resume runs the same.

A resumed run is the uninterrupted one bit for bit only when it runs the same code and the same
libraries: another commit, a modified tree or another torch, numpy, gymnasium or MuJoCo may
compute otherwise. The first part of a run records its code fingerprint and the versions of
the libraries behind its results (`mam_lab.provenance.run_code`: the CLI and the lab compute it
and hand it to `mam run`'s launcher); `mam run --resume` refuses other code, naming both,
unless forced (`--allow-other-code`), which the record keeps and the resumed learner reads: the
run is then no longer exact (`inexact_reason`).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from services.run import rundir
from services.run.rundir import write_json


def recorded(run_dir: Path) -> dict[str, Any] | None:
    """RUN_DIR/code.json, or None (a run started by an older mam, or not a run directory)."""
    try:
        data = json.loads((run_dir / rundir.CODE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("versions"), dict):
        return None
    return data


def differences(run_dir: Path, now: dict[str, Any]) -> list[str]:
    """How `now` (this code: `mam_lab.provenance.run_code`) differs from the run's code (one phrase
    each, the run's value first); [] when the same, or when the run recorded nothing to compare with."""
    was = recorded(run_dir)
    if was is None:
        return []
    out = []
    if was.get("fingerprint") != now["fingerprint"]:
        out.append(f"code {was.get('fingerprint') or 'unknown'} (the run's) vs {now['fingerprint'] or 'unknown'} "
                   "(this code)")
    old, new = was["versions"], now.get("versions", {})
    for name in sorted(set(old) | set(new)):
        if old.get(name) != new.get(name):
            out.append(f"{name} {old.get(name, 'absent')} (the run's) vs {new.get(name, 'absent')} (this code)")
    return out


def missing_fields(config: dict[str, Any]) -> list[str]:
    """The settings a run's config.json (as read) does not name, one phrase each: a run started by an
    older mam, whose resume would silently take this code's defaults for them."""
    from mam_core.config import AlgoConfig
    from services.run.config import RunConfig

    def phrase(name: str, f: dataclasses.Field) -> str:
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        return f"{name} not in the run's config.json (this code's default: {default!r})"

    algo = config.get("algo") if isinstance(config.get("algo"), dict) else {}
    return [phrase(f.name, f) for f in dataclasses.fields(RunConfig) if f.name not in config] + \
        [phrase(f"algo.{f.name}", f) for f in dataclasses.fields(AlgoConfig) if f.name not in algo]


def record(run_dir: Path, now: dict[str, Any], forced: list[str] | None = None) -> None:
    """At the start of a part: the run's code (`now`), if not recorded yet; with `forced`, the
    differences a forced resume accepted (the run is no longer exact from then on)."""
    was = recorded(run_dir)
    data = was if was is not None else dict(now)
    if forced:
        data.setdefault("forced", []).append({"part": rundir.earlier_parts(run_dir)["parts"] + 1,
                                              "differences": forced})
    if was is None or forced:
        write_json(run_dir / rundir.CODE, data, durable=True)


def record_part(run_dir: Path, now: dict[str, Any], forced: list[str]) -> str:
    """At the start of `mam run`'s part: a fresh run records `now` anew, a resumed one keeps its
    record (with the `forced` differences). What to print: the forced differences, or why the
    record could not be written (the run then stops); "" otherwise."""
    try:
        if not rundir.has_checkpoint(run_dir):
            (run_dir / rundir.CODE).unlink(missing_ok=True)
        record(run_dir, now, forced)
    except OSError as e:
        return f"[red]cannot write {run_dir / rundir.CODE}: {e.strerror or e} ({rundir.disk_free(run_dir)} free)[/]"
    return (f"[yellow]resuming with other code (--allow-other-code): {'; '.join(forced)}; the run is no longer "
            "exact[/]") if forced else ""


def inexact_reason(run_dir: Path) -> str:
    """Why the run is not exact by its code record (a resume forced onto other code), or ""."""
    data = recorded(run_dir) or {}
    forced = data.get("forced")
    if not isinstance(forced, list) or not forced or not isinstance(forced[0], dict):
        return ""
    first = forced[0]
    return (f"part {first.get('part', '?')} was resumed with other code (--allow-other-code): "
            + "; ".join(str(d) for d in first.get("differences", [])))[:1000]
