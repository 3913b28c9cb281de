"""The learner's checkpoints: verified generations with a fallback (RUN_DIR/checkpoints/).

A checkpoint generation g is three files and the replay chunks it counts:

    checkpoints/learner-<g>.pt      agent, counters and config (pickle-free: torch.load(weights_only=True))
    checkpoints/policy-<g>.npz      the actors for `load_policy` / `mam eval` (numpy)
    checkpoints/replay/chunk-*.npz  the replay buffer as append-only chunks (mam_core.replay.ReplayLog)
    checkpoints/manifest-<g>.json   sha256 and size of every file above: written last

Every file is written durably (temp file, fsync, rename, fsync of the directory) and the
manifest last, so a generation exists only once all its bytes are on disk. Two generations are
kept (KEEP); older ones and the chunks neither kept generation names are deleted after the new
manifest is in place. `checkpoints/learner.pt` and `checkpoints/policy.npz` are hard links to
the newest generation's files, the names users, `mam eval` and the tools read.

`load_checkpoint` (a resume) verifies the newest generation's manifest — every file's size and
sha256, the learner state parsed from the very bytes that were hashed — and falls back to the
previous generation when anything does not match, saying so in the log; the replay chunks are
verified again as they are read (`ReplayLog.restore`). Unverified bytes are never loaded.

A write error (a full disk, EIO, a read-only file system) while checkpointing raises
CheckpointError: the files of the unfinished generation and every temp file are removed, the
previous generation stays intact, and the message names the path and the free space there. The
learner then exits with EXIT_WRITE_ERROR and `mam run` stops the run (docs/RELIABILITY.md).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from mam_core.agent import MultiActorAgent
from mam_core.policy import POLICY_FILE, EnvSpec, save_policy_file
from mam_core.replay import ReplayBuffer, ReplayLog, fsync_dir, write_durably
from services.run import rundir
from services.run.config import RunConfig

log = logging.getLogger("mam.checkpoint")

CHECKPOINT_FILE = rundir.LEARNER_CHECKPOINT
REPLAY_DIR = rundir.REPLAY  # RUN_DIR/checkpoints/replay/chunk-<first>-<rows>.npz
KEEP = 2  # generations kept: the newest and one to fall back to
MANIFEST_FORMAT = 1
EXIT_WRITE_ERROR = 75  # the learner's exit status when it cannot write its checkpoint (EX_TEMPFAIL)
EXIT_CORRUPT = 65  # ... when no checkpoint generation verifies at a resume (EX_DATAERR)
_MANIFEST = re.compile(r"^manifest-(\d{6,})\.json$")
# run dir -> the generation this process's learner state derives from (resumed from or last
# written): the one a new generation keeps beside itself. Newer ones (damaged: the resume fell
# back past them) and older ones are deleted once the new one is complete.
_lineage: dict[str, int] = {}
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG})


class CheckpointError(Exception):
    """A checkpoint could not be written; the previous generation is intact (the message names
    the path, the error and the free space there)."""

    def __init__(self, text: str, errno_: int | None = None, filename: str | None = None) -> None:
        super().__init__(text)
        self.errno, self.filename = errno_, filename


class CheckpointCorrupt(ValueError):
    """No checkpoint generation verifies (or the one asked for does not)."""


def replay_dir(run_dir: Path) -> Path:
    return run_dir / rundir.CHECKPOINTS / REPLAY_DIR


def checkpoint_dir(run_dir: Path) -> Path:
    return run_dir / rundir.CHECKPOINTS


def learner_file(g: int) -> str:
    return f"learner-{g:06d}.pt"


def policy_file(g: int) -> str:
    return f"policy-{g:06d}.npz"


def manifest_file(g: int) -> str:
    return f"manifest-{g:06d}.json"


def generations(run_dir: Path) -> list[int]:
    """The generations that have a manifest, newest first (not verified)."""
    d = checkpoint_dir(run_dir)
    if not d.is_dir():
        return []
    found = (_MANIFEST.match(p.name) for p in d.iterdir())
    return sorted((int(m.group(1)) for m in found if m), reverse=True)


def has_checkpoint(run_dir: Path) -> bool:
    """A checkpoint generation is on disk (a restarted learner resumes from it)."""
    return bool(generations(run_dir))


def free_space(path: Path) -> str:
    """Free bytes on the file system holding `path` (or its nearest existing parent), as text."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = shutil.disk_usage(p).free
    except OSError:
        return "unknown free space"
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if free < 1024 or unit == "GiB":
            return f"{free:.0f} {unit} free" if unit == "bytes" else f"{free:.1f} {unit} free"
        free /= 1024
    return ""


def write_error_text(e: OSError, what: str = "write") -> str:
    """One line: what failed, the path, the error and the free space there."""
    path = e.filename or "?"
    return f"cannot {what} {path}: {e.strerror or e} ({free_space(Path(str(path)))} there)"


def save_checkpoint(run_dir: Path, agent: MultiActorAgent, buffer: ReplayBuffer, counters: dict[str, Any],
                    cfg: RunConfig, replay_log: ReplayLog | None = None, survivor: int | None = None,
                    extra: dict[str, Any] | None = None) -> Path:
    """Write a new checkpoint generation (see the module docstring); returns its learner file.

    With a `replay_log` the rows inserted since the previous checkpoint are appended as one
    chunk first; the state names the chunks that hold every row it counts (`replay_log`:
    inserted, manifest, sampling rng). `extra`: more entries of the state (tensors, numbers,
    strings, lists and dicts of them: what `torch.load(weights_only=True)` reads back). Raises
    CheckpointError on a write error, leaving the previous generation as it was and no temp file
    behind.
    """
    d = checkpoint_dir(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    existing = generations(run_dir)
    g = (existing[0] + 1) if existing else 1
    base = _lineage.get(str(run_dir))
    state: dict[str, Any] = {"agent": agent.state_dict(), "counters": counters,
                             "config": json.dumps(cfg.to_dict()), **(extra or {})}
    snapshot = replay_log.snapshot() if replay_log is not None else None
    written: list[Path] = []
    target = replay_dir(run_dir)  # what is being written (for the message)
    try:
        files: dict[str, dict[str, Any]] = {}
        if replay_log is not None:
            manifest = replay_log.append(buffer)
            state["replay_log"] = {"inserted": buffer.inserted, "manifest": manifest,
                                   "rng": json.dumps(buffer.rng.bit_generator.state)}
            for name in replay_log.names(manifest):
                path = replay_dir(run_dir) / name
                digest = replay_log.digests.get(name) or _sha256_file(path)
                replay_log.digests[name] = digest
                files[f"{REPLAY_DIR}/{name}"] = {"sha256": digest, "bytes": path.stat().st_size}
        data = io.BytesIO()
        torch.save(state, data)
        learner_path = target = d / learner_file(g)
        written.append(learner_path)
        files[learner_path.name] = {"sha256": write_durably(learner_path, data.getbuffer()),
                                    "bytes": data.getbuffer().nbytes}
        policy_path = target = d / policy_file(g)
        written.append(policy_path)
        _write_policy(policy_path, cfg, agent, int(counters.get("env_steps", 0)), survivor)
        files[policy_path.name] = {"sha256": _sha256_file(policy_path, fsync=True), "bytes": policy_path.stat().st_size}
        fsync_dir(d)
        meta = {"format": MANIFEST_FORMAT, "generation": g, "created": time.time(),
                "env_steps": int(counters.get("env_steps", 0)), "updates": int(agent.updates), "files": files}
        manifest_path = target = d / manifest_file(g)
        written.append(manifest_path)
        write_durably(manifest_path, json.dumps(meta, indent=1, sort_keys=True).encode())
    except OSError as e:
        if e.filename is None:
            e.filename = str(target)
        for p in written:
            p.unlink(missing_ok=True)
            p.with_name(p.name + ".tmp").unlink(missing_ok=True)
        if replay_log is not None and snapshot is not None:
            replay_log.rollback(snapshot)
        previous = f"generation {base}" if base is not None else "none"
        raise CheckpointError(f"{write_error_text(e, 'write the checkpoint')}; the previous checkpoint "
                              f"({previous}) is intact", e.errno, e.filename) from e
    _lineage[str(run_dir)] = g
    # The generation is complete. Convenience names, then the generations and chunks no longer kept.
    for src, name in ((learner_path, CHECKPOINT_FILE), (policy_path, POLICY_FILE)):
        _link(src, d / name)
    keep_chunks: set[str] = set()
    for old in existing:
        if old == base:  # KEEP = 2: the new generation and the one it derives from
            keep_chunks |= _chunk_names(d / manifest_file(old))
            continue
        for name in (manifest_file(old), learner_file(old), policy_file(old)):  # the manifest first
            (d / name).unlink(missing_ok=True)
    if replay_log is not None:
        replay_log.prune(keep_chunks)
    return learner_path


def _write_policy(path: Path, cfg: RunConfig, agent: MultiActorAgent, env_steps: int, survivor: int | None) -> None:
    from services.roles.policy_export import policy_meta

    params = [agent.actor_params(k) for k in range(cfg.algo.actors)]
    meta = policy_meta(cfg, agent.spec, env_steps=env_steps, updates=agent.updates, versions=agent.versions,
                       live=agent.live_actors, survivor=survivor)
    try:
        save_policy_file(path, params, meta)
    except BaseException:
        path.with_name(path.name + ".tmp").unlink(missing_ok=True)
        raise


def _sha256_file(path: Path, fsync: bool = False) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
        if fsync:
            os.fsync(f.fileno())
    return h.hexdigest()


def _link(src: Path, dst: Path) -> None:
    """`dst` becomes `src` (a hard link, atomically replacing it; a copy where links fail)."""
    tmp = dst.with_name(dst.name + ".tmp")
    try:
        tmp.unlink(missing_ok=True)
        try:
            os.link(src, tmp)
        except OSError as e:
            if e.errno in WRITE_ERRNOS:
                raise
            shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        log.warning("checkpoint: %s", write_error_text(e, "link"))


def _chunk_names(manifest_path: Path) -> set[str]:
    try:
        files = json.loads(manifest_path.read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return set()
    return {Path(name).name for name in files if name.startswith(f"{REPLAY_DIR}/")}


def load_replay(run_dir: Path, capacity: int | None = None, state: dict[str, Any] | None = None) -> ReplayBuffer:
    """The replay buffer a checkpoint counts (for tests and tools): every row, in a new buffer."""
    state = state if state is not None else load_checkpoint(run_dir)
    meta = state["replay_log"]
    cfg = RunConfig.from_dict(json.loads(state["config"]))
    spec = EnvSpec.from_env_id(cfg.env_id, cfg.env_kwargs)
    inserted = int(meta["inserted"])
    buffer = ReplayBuffer(capacity or max(inserted, 1), spec.obs_dim, spec.act_dim)
    ReplayLog(replay_dir(run_dir)).restore(buffer, meta["manifest"], inserted, json.loads(meta["rng"]))
    return buffer


def verify_generation(run_dir: Path, g: int) -> tuple[dict[str, Any], bytes]:
    """(manifest, the learner file's bytes) of generation `g` once every file it names has the
    size and sha256 the manifest gives; CheckpointCorrupt naming the first file that does not."""
    d = checkpoint_dir(run_dir)
    mpath = d / manifest_file(g)
    try:
        meta = json.loads(mpath.read_text())
        files = meta["files"]
        if meta.get("generation") != g or not isinstance(files, dict):
            raise ValueError("not this generation's manifest")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CheckpointCorrupt(f"{mpath} is unreadable: {type(e).__name__}: {e}") from None
    learner_bytes = b""
    for name, want in files.items():
        path = d / name
        try:
            if name == learner_file(g):
                learner_bytes = path.read_bytes()
                size, digest = len(learner_bytes), hashlib.sha256(learner_bytes).hexdigest()
            else:
                size, digest = path.stat().st_size, _sha256_file(path)
        except OSError as e:
            raise CheckpointCorrupt(f"{path} (generation {g}) cannot be read: {e.strerror or e}") from None
        if size != want.get("bytes"):
            raise CheckpointCorrupt(f"{path} (generation {g}) has {size} bytes, its manifest says {want.get('bytes')}"
                                    " (truncated or overwritten)")
        if digest != want.get("sha256"):
            raise CheckpointCorrupt(f"{path} (generation {g}) is damaged: its sha256 does not match the manifest")
    if learner_file(g) not in files:
        raise CheckpointCorrupt(f"{mpath} does not name {learner_file(g)}")
    return meta, learner_bytes


def load_checkpoint(run_dir: Path) -> dict[str, Any]:
    """The newest checkpoint generation that verifies (see `verify_generation`), as the state
    dict the learner saved, plus "checkpoint": {"generation", "skipped": [why newer ones were not
    used]}. A damaged newest generation is logged and the previous one used; FileNotFoundError
    when there is none, CheckpointCorrupt when none verifies."""
    gens = generations(run_dir)
    if not gens:
        raise FileNotFoundError(f"no checkpoint at {checkpoint_dir(run_dir)} (no manifest-*.json)")
    skipped: list[str] = []
    for g in gens:
        try:
            meta, data = verify_generation(run_dir, g)
            try:
                state = torch.load(io.BytesIO(data), weights_only=True, map_location="cpu")
            except Exception as e:  # noqa: BLE001 - verified bytes that do not parse: a writer bug
                raise CheckpointCorrupt(f"{checkpoint_dir(run_dir) / learner_file(g)}: {type(e).__name__}: {e}") \
                    from None
        except CheckpointCorrupt as e:
            log.warning("checkpoint generation %d is not usable: %s", g, e)
            skipped.append(str(e))
            continue
        if "replay_log" in state:  # the chunks' digests go with the entries: restore checks them
            digests = {Path(n).name: f["sha256"] for n, f in meta["files"].items() if n.startswith(f"{REPLAY_DIR}/")}
            entries = state["replay_log"]["manifest"]
            names = ReplayLog(replay_dir(run_dir)).names(entries)
            state["replay_log"]["manifest"] = [[int(c[0]), int(c[1]), digests.get(n)] if n in digests else list(c)
                                               for c, n in zip(entries, names)]
        if skipped:
            log.warning("resuming from checkpoint generation %d (%d transitions) instead: the newer one is damaged",
                        g, meta.get("env_steps", -1))
        state["checkpoint"] = {"generation": g, "skipped": skipped}
        _lineage[str(run_dir)] = g
        return state
    raise CheckpointCorrupt(f"no checkpoint generation in {checkpoint_dir(run_dir)} verifies: " + "; ".join(skipped))


@contextlib.contextmanager
def exit_on_write_error(run_dir: Path) -> Iterator[None]:
    """Around a role's loop: a CheckpointError, or a full disk anywhere, logs one line naming the
    path and the free space and exits with EXIT_WRITE_ERROR (`mam run` then stops the run rather
    than restart a learner that cannot write)."""
    try:
        yield
    except (CheckpointError, OSError) as e:
        if not isinstance(e, CheckpointError) and e.errno not in WRITE_ERRNOS:
            raise
        text = str(e) if isinstance(e, CheckpointError) else write_error_text(e)
        try:
            log.error("stopping: %s", text)
        finally:
            raise SystemExit(EXIT_WRITE_ERROR) from None
