"""Every random stream of a run, derived from `--seed` alone.

A stream is named by its purpose and, where there are several, an index (the slot, the
evaluation). `numpy.random.SeedSequence([seed, purpose, index])` spreads the entropy, so
streams of neighbouring seeds, slots or evaluations are independent, and none depends on a
uuid, the clock, a pid or the order in which messages arrive. The one-process reference
(mam_core.reference) and the distributed roles ask this module for the same streams, which is
half of why the two compute the same run (docs/DESIGN-DECISIONS.md, "Exact Algorithm 1").

| purpose | who draws it | index |
|---|---|---|
| `env` | (unused since episodes are seeded one by one: kept so the other purposes keep their words) | - |
| `random-actions` | a slot's uniform actions of the start phase (`action_space.seed`) | slot (and generation) |
| `noise` | a slot's Gaussian exploration noise | slot (and generation) |
| `allocation` | the referee: slot -> actor draws and the tie-break at C | - |
| `round` | the episodes of competition j (at j·A) | j |
| `curve` | the episodes of learning-curve evaluation j (at j·eval-every) | j |
| `final` | the episodes of the final evaluation when T is not a curve point | 0 |
| `elimination` | the episodes of the evaluation at C | 0 |
| `bias` | the learner's Eq. 17 rollouts at bias point j (at j·bias-every) | j (`bias_seed`) |
| `episode` | the reset of a slot's episode that starts at iteration t (`episode_seed`) | slot, t |

The replay buffer's sampling, the target-policy noise and the network initialisation take
the run seed directly (mam_core.replay, mam_core.agent), as they always did.

Every episode of a slot is reset with its own seed, from the iteration its first step belongs
to, and the slot's two sequential streams (random actions, noise) draw a fixed amount per
iteration: so a slot's state at any iteration follows from the seed, the plan and the actions
of its current episode, which is how a replacement worker continues a slot exactly
(mam_core.slot). The *generation* index is kept for streams that must differ between
incarnations; no slot stream uses it today.
"""

from __future__ import annotations

import numpy as np

PURPOSES = ("env", "random-actions", "noise", "allocation", "round", "curve", "final", "elimination", "episode")


def _words(seed: int, purpose: str, index: int, generation: int) -> list[int]:
    if purpose not in PURPOSES:
        raise ValueError(f"unknown random stream {purpose!r}; one of {', '.join(PURPOSES)}")
    if seed < 0 or index < 0 or generation < 0:
        raise ValueError(f"seed, index and generation must be >= 0, got {seed}, {index}, {generation}")
    return [int(seed), PURPOSES.index(purpose), int(index), int(generation)]


def stream(seed: int, purpose: str, index: int = 0, generation: int = 0) -> np.random.Generator:
    """The generator of one stream."""
    return np.random.default_rng(np.random.SeedSequence(_words(seed, purpose, index, generation)))


def stream_seed(seed: int, purpose: str, index: int = 0, generation: int = 0) -> int:
    """An integer seed for APIs that take one (`env.reset(seed=...)`, `action_space.seed`,
    evaluation episodes: episode e is reset with this + e)."""
    state = np.random.SeedSequence(_words(seed, purpose, index, generation)).generate_state(1, np.uint32)
    return int(state[0]) & 0x3FFF_FFFF  # leaves room for + episode under 2**31


def episode_seed(seed: int, slot: int, iteration: int) -> int:
    """The reset seed of slot `slot`'s episode whose first step is iteration `iteration`."""
    if iteration < 1:
        raise ValueError(f"iteration must be >= 1, got {iteration}")
    words = _words(seed, "episode", slot, 0) + [int(iteration)]
    return int(np.random.SeedSequence(words).generate_state(1, np.uint32)[0]) & 0x7FFF_FFFF


def evaluation_seed(seed: int, purpose: str, index: int | None = None) -> int:
    """The episodes of one evaluation: `round` j (the competition at j·A), `elimination`,
    `curve` j (at j·eval-every) or `final`. Evaluation episode e is reset with this + e."""
    if purpose == "round":
        return round_seed(seed, int(index))
    if purpose == "curve":
        return curve_seed(seed, int(index))
    if purpose == "elimination":
        return elimination_seed(seed)
    if purpose == "final":
        return final_seed(seed)
    raise ValueError(f"unknown evaluation purpose {purpose!r}")


def round_seed(seed: int, round_index: int) -> int:
    """Episodes of the competition at round_index·A (every arm with this seed sees the same)."""
    return stream_seed(seed, "round", round_index)


def curve_seed(seed: int, curve_index: int) -> int:
    """Episodes of the learning-curve evaluation at curve_index·eval-every."""
    return stream_seed(seed, "curve", curve_index)


def final_seed(seed: int) -> int:
    return stream_seed(seed, "final")


def elimination_seed(seed: int) -> int:
    return stream_seed(seed, "elimination")


def bias_seed(seed: int, point_index: int) -> int:
    """The initial states of the Eq. 17 rollouts at bias point j (every variant of a seed
    starts from the same states). Rollout r is reset with this + r."""
    return 1_000_003 * (int(seed) + 1) + int(point_index) * 1_009
