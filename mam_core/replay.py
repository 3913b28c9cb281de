"""Replay buffer: float32 numpy ring with batched O(1) insert and uniform sampling.

Row number i ever inserted sits at ring position i % capacity; `ReplayLog` writes the rows new
since the last checkpoint as an append-only chunk file and restores exactly the rows a checkpoint
counts (no pickle: `np.savez` / `np.load(allow_pickle=False)`).

Each row carries the id of the actor that produced it and that actor's policy version, so
off-policy lag and the share of experience per actor can be measured.

On a CUDA learner the rows are also kept in GPU memory (`resident`, the default there): a
mini-batch is then gathered on the GPU with one index_select per field, instead of being
gathered on the host and copied over every update. The numpy arrays stay the source of
truth (checkpoints, statistics); sampling draws the same indices either way.
"""

from __future__ import annotations

import hashlib
import io
import os
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from mam_core.accel import for_device


class Replay(Protocol):
    """What the learner, the reference and the checkpoints ask of a replay; `ReplayBuffer` is the
    uniform one. Prioritized or n-step replay is another class with these methods: rows go in in
    slot order (Algorithm 1, lines 5-10), every row keeps its insertion index (the n-th row ever
    inserted; a slot's rows are found by it, `Algorithm1.row_of`), and sampling draws from the
    replay's own seeded stream, saved with it, so a resumed run samples what it would have."""

    capacity: int
    size: int  # rows held
    inserted: int  # rows ever inserted (the learner's transition count)
    obs_dim: int
    act_dim: int

    def add_batch(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                  terminated: np.ndarray, actor: int | np.ndarray = 0, version: int | np.ndarray = 0) -> None:
        """Insert rows, in the order given (an iteration's, in slot order)."""

    def sample(self, batch_size: int, groups: int | None = None) -> dict[str, torch.Tensor]:
        """A mini-batch (or `groups` of them, one per actor) as tensors on the learner's device."""

    def sample_indices(self, batch_size: int) -> np.ndarray:
        """The positions `sample` would gather, drawn from the same stream (CUDA graphs gather them)."""

    def holds(self, row: int) -> bool:
        """Row `row` (an insertion index) is still held."""

    def rows_at(self, rows: Sequence[int] | np.ndarray) -> dict[str, np.ndarray]:
        """Held rows by insertion index (a slot's current episode, for a worker taking it over)."""

    def rows_between(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Rows `start` to `stop` (exclusive) by insertion index (the replay log's new chunk)."""

    def place_rows(self, first: int, rows: dict[str, np.ndarray]) -> None:
        """The inverse of `rows_between` (restoring from the replay log)."""

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class ReplayBuffer:
    """The uniform replay (`Replay`)."""

    FIELDS = ("obs", "action", "reward", "next_obs", "not_done")

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, device: str | torch.device = "cpu",
                 seed: int = 0, resident: bool | None = None) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = capacity
        self.device = torch.device(device)
        self.accel = for_device(self.device)  # the CUDA-only paths below (mam_core/accel.py)
        # A copy of the sampled fields on `device` (default: on CUDA only).
        self.resident = self.accel.resident_replay if resident is None else resident
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.action = np.zeros((capacity, act_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.not_done = np.zeros(capacity, np.float32)
        self.actor = np.zeros(capacity, np.int16)
        self.version = np.zeros(capacity, np.int32)
        self.rng = np.random.default_rng(seed)
        self.pos = 0
        self.size = 0
        self.inserted = 0  # rows ever inserted (the learner's transition count)
        self._mirror: dict[str, torch.Tensor] = {}
        if self.resident:
            self._mirror = {name: torch.zeros(getattr(self, name).shape, dtype=torch.float32, device=self.device)
                            for name in self.FIELDS}

    def __len__(self) -> int:
        return self.size

    @property
    def obs_dim(self) -> int:
        return self.obs.shape[1]

    @property
    def act_dim(self) -> int:
        return self.action.shape[1]

    def add_batch(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                  terminated: np.ndarray, actor: int | np.ndarray = 0, version: int | np.ndarray = 0) -> None:
        """Insert N rows at once (at most two slice copies, wrapping around the ring).

        `terminated` is the environment's terminal flag only: a time-limit truncation must be
        passed as False so the target still bootstraps.
        """
        n = len(reward)
        if n == 0:
            return
        if n > self.capacity:  # only the newest `capacity` rows survive anyway
            cut = n - self.capacity
            obs, action, reward, next_obs, terminated = (a[cut:] for a in (obs, action, reward, next_obs, terminated))
            actor = actor[cut:] if isinstance(actor, np.ndarray) else actor
            version = version[cut:] if isinstance(version, np.ndarray) else version
            self.inserted += cut
            self.pos = (self.pos + cut) % self.capacity  # row i stays at i % capacity (the replay log)
            n = self.capacity
        first = min(n, self.capacity - self.pos)
        for dst, src in ((slice(self.pos, self.pos + first), slice(0, first)),
                         (slice(0, n - first), slice(first, n))):
            if src.stop == src.start:
                continue
            self.obs[dst] = obs[src]
            self.action[dst] = action[src]
            self.reward[dst] = reward[src]
            self.next_obs[dst] = next_obs[src]
            self.not_done[dst] = 1.0 - np.asarray(terminated[src], np.float32)
            self.actor[dst] = actor[src] if isinstance(actor, np.ndarray) else actor
            self.version[dst] = version[src] if isinstance(version, np.ndarray) else version
            self._mirror_rows(dst)
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.size + n, self.capacity)
        self.inserted += n

    def sample_indices(self, batch_size: int) -> np.ndarray:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        return self.rng.integers(0, self.size, size=batch_size)

    def draw_ahead(self, incoming: int, draws: Sequence[int]) -> tuple[list[np.ndarray], int] | None:
        """The positions of the next `len(draws)` samples (`draws[j]` each) as `sample_indices`
        would draw them once `incoming` more rows are in, drawn now, and how many of them, from the
        first, hold none of the positions those rows will take (`clear`); or None, the stream left
        as it was, if the first one does. The clear samples gather rows the insertion does not
        touch, so their updates can run before the rows arrive, with the same bits (the learner's
        updates ahead of an iteration's rows); the others gather once the rows are in, at the
        positions drawn here (the stream has moved past all of them)."""
        size = min(self.size + incoming, self.capacity)
        if size == 0:
            return None
        state = self.rng.bit_generator.state
        drawn = [self.rng.integers(0, size, size=n) for n in draws]
        taken = (self.pos + np.arange(incoming)) % self.capacity
        clear = next((j for j, idx in enumerate(drawn) if np.isin(idx, taken).any()), len(drawn))
        if clear == 0:
            self.rng.bit_generator.state = state
            return None
        return drawn, clear

    def _mirror_rows(self, rows: slice) -> None:
        if not self._mirror or rows.stop == rows.start:
            return
        for name, dst in self._mirror.items():
            dst[rows].copy_(torch.from_numpy(getattr(self, name)[rows]))

    def sample(self, batch_size: int, groups: int | None = None) -> dict[str, torch.Tensor]:
        """Uniform mini-batch as float32 tensors on the buffer's device.

        `groups=K` draws K independent mini-batches at once (Algorithm 1, line 11: every actor
        samples its own): every field gets a leading axis of K, e.g. obs [K, B, obs_dim].
        """
        idx = self.sample_indices(batch_size if groups is None else groups * batch_size)
        return self.gather(idx, batch_size, groups)

    def gather(self, idx: np.ndarray, batch_size: int, groups: int | None = None) -> dict[str, torch.Tensor]:
        """The mini-batch(es) of `sample` at positions `idx` (drawn by `sample_indices` or `draw_ahead`)."""
        shape = (batch_size,) if groups is None else (groups, batch_size)
        if self._mirror:
            # Indices to the device (2 KB), then the gather happens there.
            i = torch.from_numpy(idx).to(self.device, non_blocking=self.accel.non_blocking)
            return {name: t.index_select(0, i).reshape(*shape, *t.shape[1:]) for name, t in self._mirror.items()}
        idx = idx.reshape(shape)
        pin = self.accel.pin_memory
        out = {}
        for name in self.FIELDS:
            t = torch.from_numpy(getattr(self, name)[idx])
            if pin:  # page-locked staging: the copy to the GPU runs asynchronously
                t = t.pin_memory().to(self.device, non_blocking=self.accel.non_blocking)
            out[name] = t
        return out

    def actor_share(self) -> np.ndarray:
        """Fraction of stored rows produced by each actor id (up to the largest id seen)."""
        if self.size == 0:
            return np.zeros(0)
        counts = np.bincount(self.actor[: self.size].astype(np.int64))
        return counts / counts.sum()

    # -- checkpoints: arrays and ints only -----------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        n = self.size
        return {
            "obs": torch.from_numpy(self.obs[:n].copy()), "action": torch.from_numpy(self.action[:n].copy()),
            "reward": torch.from_numpy(self.reward[:n].copy()), "next_obs": torch.from_numpy(self.next_obs[:n].copy()),
            "not_done": torch.from_numpy(self.not_done[:n].copy()), "actor": torch.from_numpy(self.actor[:n].copy()),
            "version": torch.from_numpy(self.version[:n].copy()),
            "pos": self.pos, "size": self.size, "inserted": self.inserted,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        n = int(state["size"])
        if n > self.capacity:
            raise ValueError(f"checkpoint holds {n} rows, buffer capacity is {self.capacity}")
        for name in ("obs", "action", "reward", "next_obs", "not_done", "actor", "version"):
            getattr(self, name)[:n] = state[name].numpy()
        self.pos, self.size, self.inserted = int(state["pos"]), n, int(state["inserted"])
        self.rng.bit_generator.state = state["rng"]
        self._mirror_rows(slice(0, n))

    # -- incremental persistence: the rows in insertion order -----------------------------------
    def _spans(self, start: int, stop: int) -> list[tuple[slice, slice]]:
        """(ring slice, offset slice) pairs covering insertion indices [start, stop): at most two."""
        n = stop - start
        if n > self.capacity:
            raise ValueError(f"{n} rows do not fit in a ring of {self.capacity}")
        pos = start % self.capacity
        first = min(n, self.capacity - pos)
        spans = [(slice(pos, pos + first), slice(0, first))]
        if n > first:
            spans.append((slice(0, n - first), slice(first, n)))
        return spans

    def rows_between(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """The rows inserted as the `start`-th up to the `stop`-th (exclusive): views of the
        ring when they do not wrap around its end, else copies. Use them before inserting more.

        Insertion index i lives at ring position i % capacity while it is among the newest
        `size` rows; older ones have been overwritten and cannot be asked for.
        """
        oldest = self.inserted - self.size
        if not oldest <= start <= stop <= self.inserted:
            raise ValueError(f"rows [{start}, {stop}) not held (held: [{oldest}, {self.inserted}))")
        spans = self._spans(start, stop)
        out = {}
        for name in PERSISTED:
            a = getattr(self, name)
            out[name] = a[spans[0][0]] if len(spans) == 1 else np.concatenate([a[ring] for ring, _ in spans])
        return out

    def holds(self, row: int) -> bool:
        """Insertion index `row` is among the newest `size` rows (not yet overwritten)."""
        return self.inserted - self.size <= row < self.inserted

    def rows_at(self, rows: Sequence[int] | np.ndarray) -> dict[str, np.ndarray]:
        """Copies of the rows with these insertion indices, field by field (PERSISTED); ValueError
        for one no longer (or not yet) held."""
        rows = np.asarray(rows, np.int64)
        if len(rows) and not (self.holds(int(rows.min())) and self.holds(int(rows.max()))):
            raise ValueError(f"rows {rows.min()}..{rows.max()} not all held (held: "
                             f"[{self.inserted - self.size}, {self.inserted}))")
        pos = rows % self.capacity
        return {name: getattr(self, name)[pos] for name in PERSISTED}

    def place_rows(self, first: int, rows: dict[str, np.ndarray]) -> None:
        """Put rows with insertion indices first, first+1, ... at their ring positions
        (the inverse of `rows_between`); the caller sets `inserted`/`size`/`pos` afterwards."""
        n = len(rows["reward"])
        for ring, part in self._spans(first, first + n):
            for name in PERSISTED:
                getattr(self, name)[ring] = rows[name][part]
            self._mirror_rows(ring)


PERSISTED = ("obs", "action", "reward", "next_obs", "not_done", "actor", "version")
CHUNK_PREFIX = "chunk-"


class ReplayLog:
    """The replay buffer on disk as append-only chunk files, one per checkpoint.

    A chunk holds the rows inserted between two checkpoints, in insertion order, as an
    uncompressed `.npz` of plain arrays (written with `np.savez`, read with
    `np.load(allow_pickle=False)`: nothing is unpickled). Its name carries the insertion
    index of its first row and its row count (`chunk-<first>-<rows>.npz`). A checkpoint writes
    only the rows new since the previous one, and its manifest (a list of `[first, rows]`,
    stored in the checkpoint itself) names the chunks that hold the rows it counts: a chunk
    written by a checkpoint that never completed is not in any manifest and is ignored, then
    deleted. Once the ring has wrapped, chunks entirely older than the newest `capacity` rows
    leave the manifest and are deleted, so the directory holds at most about one buffer and
    one checkpoint interval of rows.

    Every chunk is written durably (a temp file, fsync, rename, fsync of the directory) and its
    sha256 is kept in `digests` (name -> hex) for the checkpoint's manifest
    (services/roles/checkpoint.py); `restore` verifies a chunk against a digest given with its manifest
    entry (`[first, rows, sha256]`) before it parses a byte of it. `snapshot`/`rollback` undo an
    `append` whose checkpoint could not be completed (a full disk): the chunk is deleted.
    """

    def __init__(self, directory: str | os.PathLike) -> None:
        self.directory = Path(directory)
        self.manifest: list[list[int]] = []
        self.persisted = 0  # rows ever inserted that a chunk in the manifest covers
        self.digests: dict[str, str] = {}  # chunk file name -> sha256 (hex) of its bytes

    def path(self, first: int, rows: int) -> Path:
        return self.directory / f"{CHUNK_PREFIX}{first:012d}-{rows}.npz"

    def append(self, buffer: ReplayBuffer) -> list[list[int]]:
        """Write the rows inserted since the last call as one chunk; returns the new manifest.

        Rows that were inserted and already overwritten since the last call (the ring wrapped
        more than once between two checkpoints) cannot be written; they would not be in the
        buffer anyway, and the manifest starts after them. On a write error (OSError) nothing
        changes: the temp file is removed and the manifest stays as it was.
        """
        self.directory.mkdir(parents=True, exist_ok=True)
        start = max(self.persisted, buffer.inserted - buffer.size)
        stop = buffer.inserted
        if stop > start:
            rows = buffer.rows_between(start, stop)
            path = self.path(start, stop - start)
            data = io.BytesIO()
            np.savez(data, **rows)
            self.digests[path.name] = write_durably(path, data.getbuffer())
            self.manifest.append([start, stop - start])
        self.persisted = stop
        oldest = stop - buffer.capacity  # rows before this are no longer in the buffer
        self.manifest = [[f, n] for f, n in self.manifest if f + n > oldest]
        return [list(c) for c in self.manifest]

    def names(self, manifest: list[list[int]] | None = None) -> list[str]:
        """The chunk file names of `manifest` (default: the current one)."""
        return [self.path(int(c[0]), int(c[1])).name for c in (self.manifest if manifest is None else manifest)]

    def snapshot(self) -> tuple[list[list[int]], int, dict[str, str]]:
        return [list(c) for c in self.manifest], self.persisted, dict(self.digests)

    def rollback(self, snapshot: tuple[list[list[int]], int, dict[str, str]]) -> None:
        """Undo the appends since `snapshot`: their chunk files are deleted (a checkpoint failed)."""
        manifest, persisted, digests = snapshot
        keep = set(self.names(manifest))
        for name in set(self.names()) - keep:
            (self.directory / name).unlink(missing_ok=True)
        self.manifest, self.persisted, self.digests = manifest, persisted, digests

    def prune(self, keep: set[str] | frozenset[str] = frozenset()) -> int:
        """Delete chunk files that neither the current manifest nor `keep` (names) names (call
        after the checkpoint that holds the manifest is on disk; `keep`: the chunks of the
        previous checkpoint generation). Returns how many were deleted."""
        keep = set(self.names()) | set(keep)
        deleted = 0
        if not self.directory.is_dir():
            return 0
        for p in self.directory.iterdir():
            if p.name.startswith(CHUNK_PREFIX) and p.name not in keep:
                p.unlink(missing_ok=True)
                deleted += 1
        self.digests = {k: v for k, v in self.digests.items() if k in keep}
        return deleted

    def restore(self, buffer: ReplayBuffer, manifest: list[list[Any]], inserted: int,
                rng_state: dict[str, Any] | None = None) -> int:
        """Refill an empty `buffer` with the newest min(capacity, inserted) rows that
        `manifest` names, at the ring positions they had; returns the rows loaded.

        A manifest entry is `[first, rows]` or `[first, rows, sha256]`; with a digest the chunk's
        bytes are checked before they are parsed. Raises ValueError, naming the file, if a chunk
        is missing, damaged (digest mismatch, not a readable .npz), malformed, or the manifest
        does not cover those rows contiguously: a resumed learner must have every row its
        checkpoint counted.
        """
        want_from = max(0, inserted - buffer.capacity)
        chunks = sorted((int(c[0]), int(c[1]), str(c[2]) if len(c) > 2 else None) for c in manifest)
        expected = want_from
        loaded = 0
        for first, n, digest in chunks:
            if first + n <= want_from:
                continue
            if first > expected or first + n > inserted:
                raise ValueError(f"replay chunks do not cover rows [{want_from}, {inserted}): "
                                 f"chunk [{first}, {first + n}) after row {expected}")
            rows = self._read(self.path(first, n), n, buffer, digest)
            skip = max(0, want_from - first)
            if skip:
                rows = {k: v[skip:] for k, v in rows.items()}
            buffer.place_rows(first + skip, rows)
            loaded += n - skip
            expected = first + n
        if expected != inserted and inserted > want_from:
            raise ValueError(f"replay chunks end at row {expected}, the checkpoint counts {inserted}")
        buffer.inserted = inserted
        buffer.size = min(inserted, buffer.capacity)
        buffer.pos = inserted % buffer.capacity
        if rng_state is not None:
            buffer.rng.bit_generator.state = rng_state
        self.manifest = [[f, n] for f, n, _ in chunks if f + n > want_from]
        self.digests = {self.path(f, n).name: d for f, n, d in chunks if d is not None and f + n > want_from}
        self.persisted = inserted
        return loaded

    @staticmethod
    def _read(path: Path, n: int, buffer: ReplayBuffer, digest: str | None = None) -> dict[str, np.ndarray]:
        if not path.is_file():
            raise ValueError(f"replay chunk {path} is missing")
        try:
            data = path.read_bytes()
        except OSError as e:
            raise ValueError(f"replay chunk {path} cannot be read: {e}") from None
        if digest is not None and hashlib.sha256(data).hexdigest() != digest:
            raise ValueError(f"replay chunk {path} is damaged: its sha256 does not match the checkpoint's manifest "
                             f"({len(data)} bytes)")
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                rows = {name: z[name] for name in PERSISTED}
        except (zipfile.BadZipFile, ValueError, OSError, KeyError, EOFError) as e:
            raise ValueError(f"replay chunk {path} is damaged: {type(e).__name__}: {e}") from None
        for name in PERSISTED:
            ref = getattr(buffer, name)
            a = rows[name]
            if a.dtype != ref.dtype or a.shape != (n, *ref.shape[1:]):
                raise ValueError(f"{path}: {name} is {a.dtype}{list(a.shape)}, want {ref.dtype}{[n, *ref.shape[1:]]}")
        return rows


def write_durably(path: Path, data: bytes | memoryview) -> str:
    """Write `data` to `path` atomically and durably: a temp file beside it, fsync, rename, fsync
    of the directory. Returns the sha256 (hex) of `data`. On any OSError the temp file is
    removed and `path` is untouched (the error propagates)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.filename is None:  # a failed write() names no file: name the one being written
            raise OSError(e.errno, e.strerror, str(path)) from e
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
    return hashlib.sha256(data).hexdigest()


def fsync_dir(directory: Path) -> None:
    """Make a rename in `directory` durable (best effort: some filesystems refuse)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
