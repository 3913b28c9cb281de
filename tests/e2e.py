"""Helpers for end-to-end tests: real `mam` processes on loopback, their run directories."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from services.run.rundir import read_jsonl

ROOT = Path(__file__).resolve().parents[1]


def unique_run(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


def mam(*args: str, timeout: float = 300, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """`mam ARGS` as a user runs it; raises with the output on a non-zero exit."""
    env = dict(os.environ, COLUMNS="160", PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=cwd, env=env, text=True,
                          capture_output=True, timeout=timeout)
    if proc.returncode != 0:
        raise AssertionError(f"mam {' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


def spawn(module: str, *args: str, log: Path, env: dict[str, str] | None = None) -> subprocess.Popen:
    """`python -m services.roles.MODULE ARGS` in its own session, output to `log`; `env` adds variables."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as out:
        return subprocess.Popen([sys.executable, "-m", f"services.roles.{module}", *args], cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                env=dict(os.environ, PYTHONWARNINGS="ignore", **(env or {})))


def stop(*procs: subprocess.Popen, timeout: float = 20.0) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


def processes_of(run: str) -> list[str]:
    """Command lines of live processes that mention this run (none must be left behind)."""
    out = subprocess.run(["ps", "-eo", "pid,args"], capture_output=True, text=True).stdout.splitlines()
    return [line for line in out if run in line and "services." in line]


def load(run_dir: Path) -> dict[str, Any]:
    return {
        "config": json.loads((run_dir / "config.json").read_text()),
        "summary": json.loads((run_dir / "summary.json").read_text()),
        "transport": json.loads((run_dir / "transport.json").read_text()),
        "learner": read_jsonl(run_dir / "learner.jsonl"),
        "eval": read_jsonl(run_dir / "eval.jsonl"),
        "allocation": read_jsonl(run_dir / "allocation.jsonl"),
        "workers": [json.loads(p.read_text()) for p in sorted((run_dir / "workers").glob("*.json"))],
    }


def assert_exactly_once(run: dict[str, Any]) -> None:
    """Every transition a worker sent reached the replay buffer once: per worker incarnation."""
    t = run["transport"]
    assert t["lost"] == 0 and t["duplicates"] == 0 and t["rejected"] == {}
    sent = {f"{w['worker']}/{w['incarnation']}": w["sent_rows"] for w in run["workers"]}
    assert sent == t["rows_per_stream"]
    assert sum(sent.values()) == t["env_steps"]


def learner_iterations(run_dir: Path) -> int:
    """The iterations of the learner's last learner.jsonl row (0 before the first)."""
    rows = read_jsonl(run_dir / "learner.jsonl") if (run_dir / "learner.jsonl").is_file() else []
    return rows[-1]["iterations"] if rows else 0


def pid_of(pattern: str) -> int | None:
    """The first live process whose command line matches `pattern` (pgrep -f)."""
    out = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout.split()
    return int(out[0]) if out else None


def signal_when(run_dir: Path, pattern: str, iterations: int, sig: int, proc: subprocess.Popen | None = None,
                timeout: float = 180.0) -> int:
    """Send `sig` to the process matching `pattern` once the run's learner has logged `iterations`
    iterations; its pid. Fails if that does not happen within `timeout` s (or `proc` ends first)."""
    deadline = time.monotonic() + timeout
    while learner_iterations(run_dir) < iterations or pid_of(pattern) is None:
        assert time.monotonic() < deadline, f"no {pattern!r} at iteration {iterations} within {timeout:.0f} s"
        assert proc is None or proc.poll() is None, "the run ended first"
        time.sleep(0.2)
    pid = pid_of(pattern)
    assert pid is not None
    os.kill(pid, sig)
    return pid


class LinkProxy:
    """A TCP proxy on loopback in front of `port`: a client that connects to `self.port` reaches
    the listener there. `blackhole()` drops what clients send (the other way still flows) until
    `cut()` closes every connection; clients then reconnect through it, and it forwards again."""

    def __init__(self, port: int) -> None:
        self.target, self.pairs = port, []
        self.dropping, self.closed = threading.Event(), threading.Event()
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self.closed.is_set():
            try:
                client, _ = self.server.accept()
                upstream = socket.create_connection(("127.0.0.1", self.target))
            except OSError:
                continue
            self.pairs.append((client, upstream))
            threading.Thread(target=self._pump, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(upstream, client, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, upward: bool) -> None:
        try:
            while data := src.recv(65536):
                if not (upward and self.dropping.is_set()):
                    dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    def blackhole(self) -> None:
        self.dropping.set()

    def cut(self) -> None:
        pairs, self.pairs = self.pairs, []
        for pair in pairs:
            for s in pair:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()
        self.dropping.clear()

    def close(self) -> None:
        self.closed.set()
        self.server.close()
        self.cut()
