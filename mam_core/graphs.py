"""CUDA graphs of the learner's update: each phase is one graph launch instead of ~60 kernels.

A K=2 MA-TD3 update on an H200 keeps the GPU busy for about a tenth of its wall time when
launched op by op: the rest is Python and kernel launches (docs/PERFORMANCE.md, "GPU"). Here
the two phases of an update (`MultiActorAgent.critic_step`, `.actor_step`) are captured once
each and replayed:

- **Sampling on the device.** The replay keeps its rows in GPU memory (`ReplayBuffer`'s
  resident copy); `stage()` draws the indices from the replay's own numpy stream (the same
  indices as `ReplayBuffer.sample`) into page-locked memory and copies them to a fixed device
  tensor; the critic graph gathers the mini-batch(es) there and the actor graph reads them.
- **Random draws outside the graph.** The agent's noise (`draw_noise`) is drawn from its
  generator into fixed tensors right before a replay, in the order the eager update draws it,
  so the stream of `noise_gen` is the eager one.
- **Warm-up leaves no trace.** Capturing needs a few real steps (the optimizers create their
  state). The parameters, targets, optimizer state and generator are saved before and written
  back in place after, so the graphed run starts from the state the eager one would.
- **Recapture on change.** The elimination (other index tensors, maybe η = 0) and a checkpoint
  load (new optimizer state tensors) bump `agent.structure`; the next update captures again.

Exactness is the GPU's own: the same seed gives the same run on the same GPU model, driver,
CUDA and torch (cuBLAS picks its kernels by those). The graphed update replays the eager
update's kernels; the device check (benchmarks/gpu.sh) compares the two over 100 updates.

Off by `MAM_CUDA_GRAPHS=0`; never on a CPU (`Accel.cuda_graphs`).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator, MutableMapping, Sequence
from typing import Any

import torch

GRAPHS_ENV = "MAM_CUDA_GRAPHS"
WARMUP_STEPS = 3  # eager steps on a side stream before capturing (torch's whole-network recipe)
_HOST_SLOTS = 4  # page-locked index buffers in turn: one is reused only after its copy ran


def enabled() -> bool:
    """False where `MAM_CUDA_GRAPHS=0` (or off / false / no)."""
    return os.environ.get(GRAPHS_ENV, "1").strip().lower() not in ("0", "off", "false", "no")


def usable(agent: Any, buffer: Any) -> bool:
    """Can `agent` update through graphs from `buffer`: a device that takes them, a replay
    resident on it, and not switched off."""
    return bool(agent.accel.cuda_graphs and getattr(buffer, "_mirror", None) and enabled())


class Staged:
    """A mini-batch whose indices are on the device: the token `UpdateGraphs.stage` returns."""

    __slots__ = ()


class LazyMetrics(MutableMapping):
    """An update's metrics as device tensors, read to floats only when looked at (one device
    sync then, not one per update). Merging two keeps both unread."""

    def __init__(self, names: Sequence[str], values: torch.Tensor) -> None:
        self._parts: list[tuple[Sequence[str], torch.Tensor]] = [(names, values)]
        self._read: dict[str, float] | None = None

    def _resolve(self) -> dict[str, float]:
        if self._read is None:
            self._read = {}
            for names, values in self._parts:
                self._read.update(zip(names, values.tolist()))
            self._parts = []
        return self._read

    def update(self, other: Any = (), /, **kw: Any) -> None:
        if isinstance(other, LazyMetrics) and self._read is None and other._read is None and not kw:
            self._parts.extend(other._parts)
            return
        self._resolve().update(other, **kw)

    def __getitem__(self, key: str) -> float:
        return self._resolve()[key]

    def __setitem__(self, key: str, value: float) -> None:
        self._resolve()[key] = value

    def __delitem__(self, key: str) -> None:
        del self._resolve()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._resolve())

    def __len__(self) -> int:  # without a sync: the names are known
        return len(self._read) if self._read is not None else sum(len(n) for n, _ in self._parts)


class UpdateGraphs:
    """The captured critic and actor phases of one agent over one replay buffer."""

    def __init__(self, agent: Any, buffer: Any, batch_size: int) -> None:
        self.agent = agent
        self.buffer = buffer
        groups = agent.batch_groups
        self.shape = (batch_size,) if groups is None else (groups, batch_size)
        self.rows = batch_size * (groups or 1)
        device = agent.device
        self.index = torch.zeros(self.rows, dtype=torch.long, device=device)
        self._host = [torch.zeros(self.rows, dtype=torch.long).pin_memory() for _ in range(_HOST_SLOTS)]
        self._copied: list[torch.cuda.Event | None] = [None] * _HOST_SLOTS
        self._slot = 0
        self._token = Staged()
        self.capturing = False  # draw_noise hands out the fixed noise tensors
        self._draws: list[torch.Tensor] = []  # the phase being recorded
        self._cursor = 0
        self._critic_noise: list[torch.Tensor] = []
        self._actor_noise: list[torch.Tensor] = []
        self._structure: int | None = None  # agent.structure at the capture
        self.captures = 0
        self.failed = ""  # why capturing failed (then every phase runs eagerly)
        self._eager_batch: dict[str, torch.Tensor] = {}

    # -- sampling ---------------------------------------------------------------------------------
    def stage(self) -> Staged:
        """The next mini-batch: its indices (the replay's own stream) copied to the device."""
        slot = self._slot = (self._slot + 1) % _HOST_SLOTS
        if self._copied[slot] is not None:
            self._copied[slot].synchronize()  # that buffer's earlier copy has run
        else:
            self._copied[slot] = torch.cuda.Event()
        self._host[slot].numpy()[:] = self.buffer.sample_indices(self.rows)
        self.index.copy_(self._host[slot], non_blocking=True)
        self._copied[slot].record()
        return self._token

    def staged(self, batch: Any) -> bool:
        return batch is self._token

    def _gather(self) -> dict[str, torch.Tensor]:
        return {name: t.index_select(0, self.index).reshape(*self.shape, *t.shape[1:])
                for name, t in self.buffer._mirror.items()}

    # -- the noise the phases draw ------------------------------------------------------------------
    def noise(self, shape: tuple[int, ...]) -> torch.Tensor:
        """During warm-up and capture: the phase's next fixed noise tensor (made on first use)."""
        if self._cursor == len(self._draws):
            self._draws.append(torch.zeros(shape, device=self.agent.device))
        t = self._draws[self._cursor]
        if tuple(t.shape) != tuple(shape):
            raise RuntimeError(f"CUDA graph: noise draw {self._cursor} has shape {tuple(shape)}, "
                               f"captured {tuple(t.shape)}")
        self._cursor += 1
        return t

    def _phase(self, draws: list[torch.Tensor]) -> None:
        self._draws, self._cursor = draws, 0

    def _draw(self, draws: list[torch.Tensor]) -> None:
        gen = self.agent.noise_gen
        for t in draws:
            t.normal_(generator=gen)  # what torch.randn(shape, generator=gen) draws

    # -- replays ------------------------------------------------------------------------------------
    def critics(self) -> torch.Tensor:
        """The critic phase on the staged mini-batch; its metrics (a copy: the next replay
        overwrites the graph's own)."""
        if not self._ensure():
            self._eager_batch = self._gather()
            return self.agent.critic_step(self._eager_batch)
        self._draw(self._critic_noise)
        self._critic_graph.replay()
        return self._critic_out.clone()

    def actors(self) -> torch.Tensor:
        """The actor phase on the mini-batch the critic phase gathered."""
        if not self._ensure():
            return self.agent.actor_step(self._eager_batch)
        self._draw(self._actor_noise)
        self._actor_graph.replay()
        return self._actor_out.clone()

    def metrics(self, names: Sequence[str], values: torch.Tensor) -> LazyMetrics:
        return LazyMetrics(names, values)

    # -- capture ------------------------------------------------------------------------------------
    def _ensure(self) -> bool:
        """Graphs of the agent as it is now: captured again after a change; False where capturing
        failed (`failed` says why): the phases then run eagerly, on the same draws and indices."""
        if self.failed:
            return False
        if self._structure != self.agent.structure:
            try:
                self.capture()
            except Exception as e:  # noqa: BLE001 - a device or torch that cannot capture: run eagerly
                self.failed = f"{type(e).__name__}: {e}"[:500]
                warnings.warn(f"mam: CUDA graphs off for this learner ({self.failed}); updating eagerly",
                              RuntimeWarning, stacklevel=3)
                return False
            # The elimination comes between a critic and an actor phase: the actor graph reads the
            # batch the new critic graph would have gathered, so gather it now.
            with torch.no_grad():
                for name, t in self._gather().items():
                    self._batch[name].copy_(t)
        return True

    def _optimizers(self) -> list[torch.optim.Optimizer]:
        a = self.agent
        return [o for o in (a.critic_opt, a.actor_opt, a.alpha_opt) if o is not None]

    def _state_tensors(self) -> list[torch.Tensor]:
        """Every tensor a step changes, besides optimizer state: parameters and targets."""
        a = self.agent
        modules = [m for m in (a.actor, a.critic, a.actor_target, a.critic_target) if m is not None]
        tensors = [p for m in modules for p in m.parameters()]
        return tensors + ([a.log_alpha] if a.stochastic else [])

    def capture(self) -> None:
        """Capture both phases after a warm-up that is then undone (see the module's notes)."""
        a = self.agent
        params = self._state_tensors()
        saved = [p.detach().clone() for p in params]
        opt_saved = {id(t): t.detach().clone() for o in self._optimizers() for s in o.state.values()
                     for t in s.values() if isinstance(t, torch.Tensor)}
        gen_state = a.noise_gen.get_state()
        self._critic_noise, self._actor_noise = [], []
        self._critic_graph = self._actor_graph = None
        flags = [(g, g.get("capturable", False)) for o in self._optimizers() for g in o.param_groups]
        for g, _ in flags:
            g["capturable"] = True  # the optimizers' step may be captured (fused Adam: the same kernel)
        self.capturing = True
        try:
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(WARMUP_STEPS):
                    batch = self._gather()
                    self._phase(self._critic_noise)
                    a.critic_step(batch)
                    self._phase(self._actor_noise)
                    a.actor_step(batch)
            torch.cuda.current_stream().wait_stream(side)
            critic_graph, actor_graph = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
            self._phase(self._critic_noise)
            with torch.cuda.graph(critic_graph):
                self._batch = self._gather()
                self._critic_out = a.critic_step(self._batch)
            self._phase(self._actor_noise)
            with torch.cuda.graph(actor_graph):
                self._actor_out = a.actor_step(self._batch)
        finally:
            self.capturing = False
            for g, flag in flags:
                g["capturable"] = flag
            with torch.no_grad():  # undo the warm-up, in place (the graphs hold these addresses)
                for p, v in zip(params, saved):
                    p.copy_(v)
                for o in self._optimizers():
                    for s in o.state.values():
                        for t in s.values():
                            if isinstance(t, torch.Tensor):
                                t.copy_(opt_saved[id(t)]) if id(t) in opt_saved else t.zero_()
            a.noise_gen.set_state(gen_state)
            torch.cuda.synchronize()
        self._critic_graph, self._actor_graph = critic_graph, actor_graph
        self._structure = a.structure
        self.captures += 1

