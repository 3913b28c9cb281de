"""torch.optim's one-second import, which mam never needs.

`torch.optim.Optimizer`'s methods that build, save and load an optimizer (`add_param_group`,
which its constructor calls, `state_dict`, `load_state_dict`, `zero_grad`) are wrapped by
`torch._disable_dynamo`, whose first call imports `torch._dynamo` (about 1.0 s on the Zen 4 box
with torch 2.13, as long as importing torch itself) only to keep the method out of what
`torch.compile` traces. mam never compiles (mam_core/accel.py). In a learner that import sat
between the process start and the run's config going out, so every worker and the referee
waited for it: `defer_dynamo_import` marks those methods as handled, without tracing them (what
the wrapper would cache after its import, less the import), so building the agent imports
nothing. `step` is wrapped twice: by the profiler's hook runner (a `record_function` label and
the step hooks) and by `_use_grad_for_differentiable`, which imports `torch._dynamo` to mark
graph breaks around the step and turns gradients off for it. `step(opt)` calls the step itself,
with gradients off, where neither wrapper has work to do (no step hooks, not `differentiable`):
so a learner never imports `torch._dynamo`, and the second of CPU it took in the random phase
is spared.

Nothing computed changes: the same methods run on the same arguments (tests/test_optim_start.py
compares the parameters after 40 updates both ways). A torch whose wrapper is not the one this
module recognises is left as it is (`defer_dynamo_import` returns 0).
"""

from __future__ import annotations

import inspect
import sys
from collections.abc import Callable
from typing import Any

import torch
from torch.optim import optimizer as _torch_optimizer

_MODULE = "torch._dynamo"
_MARK = "__dynamo_disable"  # where `torch._disable_dynamo`'s wrapper caches what it calls
UNWRAP = True  # False: `step` calls `opt.step()` with its wrappers (tests compare the two)
_steps: dict[type, Callable[..., Any]] = {}  # an optimizer class -> its step, unwrapped


def _wrapper_code() -> object:
    """The code object of `torch._disable_dynamo`'s wrapper (making one imports nothing)."""
    return torch._disable_dynamo(lambda: None).__code__


def defer_dynamo_import(classes: tuple[type, ...] = (torch.optim.Optimizer,)) -> int:
    """Mark `classes`' `torch._disable_dynamo`-wrapped methods as handled, so that calling them
    does not import `torch._dynamo`. The number of methods marked (0 once it is imported)."""
    if dynamo_imported():
        return 0
    code, marked = _wrapper_code(), 0
    for cls in classes:
        for attr in vars(cls).values():
            fn = getattr(attr, "__wrapped__", None)
            if getattr(attr, "__code__", None) is code and fn is not None and getattr(fn, _MARK, None) is None:
                setattr(fn, _MARK, fn)
                marked += 1
    return marked


def dynamo_imported() -> bool:
    return _MODULE in sys.modules


def step(opt: torch.optim.Optimizer) -> None:
    """`opt.step()`, without the wrappers where they have nothing to do (module docstring)."""
    hooks = _torch_optimizer._global_optimizer_pre_hooks or _torch_optimizer._global_optimizer_post_hooks
    if not UNWRAP or hooks or opt._optimizer_step_pre_hooks or opt._optimizer_step_post_hooks or \
            opt.defaults.get("differentiable", False) or "step" in vars(opt):  # (an LR scheduler's counter)
        opt.step()
        return
    raw = _steps.get(type(opt))
    if raw is None:
        raw = _steps[type(opt)] = inspect.unwrap(type(opt).step)
    with torch.no_grad():
        raw(opt)
