"""torch.optim's one-second import, moved to where a learner waits anyway.

`torch.optim.Optimizer`'s methods that build, save and load an optimizer (`add_param_group`,
which its constructor calls, `state_dict`, `load_state_dict`, `zero_grad`) are wrapped by
`torch._disable_dynamo`, whose first call imports `torch._dynamo` (about 1.0 s on the Zen 4 box
with torch 2.13, as long as importing torch itself) only to keep the method out of what
`torch.compile` traces. mam never compiles (mam_core/accel.py). In a learner that import sat
between the process start and the run's config going out, so every worker and the referee
waited for it: `defer_dynamo_import` marks those methods as handled, without tracing them (what
the wrapper would cache after its import, less the import), so building the agent imports
nothing. The first `step` still imports it (its `_use_grad_for_differentiable` does):
`import_dynamo` does that where the learner waits for rows anyway (the random phase's first
iteration), while the workers step.

Nothing computed changes: the wrappers call the same methods. A torch whose wrapper is not the
one this module recognises is left as it is (`defer_dynamo_import` returns 0).
"""

from __future__ import annotations

import importlib
import sys

import torch

_MODULE = "torch._dynamo"
_MARK = "__dynamo_disable"  # where `torch._disable_dynamo`'s wrapper caches what it calls


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


def import_dynamo() -> None:
    """Import `torch._dynamo` now (what the first optimizer step would do)."""
    importlib.import_module(_MODULE)
