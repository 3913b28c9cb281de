"""The one switch for what only an accelerator does: `for_device(device)` gives an `Accel`.

Every code path that only CUDA takes reads its field here instead of testing the device
itself: page-locked staging and non-blocking host-to-device copies (`mam_core.replay`), the
replay's device-resident copy, and the bf16 support check of a GPU. A CPU device gets all of
them off, so CPU runs take exactly the code they took before this module existed; what only
the CPU does (glibc keeping freed blocks for torch's malloc-based allocator, `mam_core.agent`)
is a field too.

CUDA graphs of the update (`mam_core.graphs`) are on for CUDA (`MAM_CUDA_GRAPHS=0` turns them
off); `torch.compile` is not used.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Accel:
    """What a device's code paths do; build it with `for_device`."""

    kind: str  # torch device type: "cpu", "cuda", ...
    pin_memory: bool = False  # page-locked host staging for host -> device copies
    non_blocking: bool = False  # asynchronous host -> device copies (needs pinned memory to overlap)
    resident_replay: bool = False  # the replay keeps its sampled fields in device memory (gather there)
    host_allocator_tuning: bool = False  # glibc keeps freed blocks (torch's CPU allocator is malloc)
    cuda_graphs: bool = False  # the update's two phases replay as CUDA graphs (mam_core/graphs.py)

    @property
    def cuda(self) -> bool:
        return self.kind == "cuda"

    def bf16_supported(self) -> bool | None:
        """On CUDA: does the GPU compute bf16 natively (`torch.cuda.is_bf16_supported()`, Ampere
        and later)? None elsewhere: a CPU's bf16 is judged from its flags
        (`services.cli.cpu.native_bf16_cpu`). Asked on demand, so building an `Accel` never
        initialises CUDA."""
        return bool(torch.cuda.is_bf16_supported()) if self.cuda else None


CPU = Accel("cpu", host_allocator_tuning=True)
CUDA = Accel("cuda", pin_memory=True, non_blocking=True, resident_replay=True, cuda_graphs=True)


def for_device(device: str | torch.device) -> Accel:
    """The `Accel` of a device ("cpu", "cuda", "cuda:1", torch.device). Other device types get
    every accelerator path off, like the CPU, without the CPU-only allocator tuning."""
    kind = torch.device(device).type
    if kind == "cuda":
        return CUDA
    if kind == "cpu":
        return CPU
    return Accel(kind)
