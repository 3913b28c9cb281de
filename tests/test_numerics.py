"""The numerics digest: the same code and seed give the same digest, another seed another."""

from __future__ import annotations

from mam_lab.numerics import numerics

TINY = dict(hidden=(8, 8), batch_size=8)


def test_the_digest_reproduces_and_tells_seeds_apart() -> None:
    a = numerics("Pendulum-v1", 100, 1, **TINY)
    assert set(a) == {"paper", "equal-data"}
    assert numerics("Pendulum-v1", 100, 1, **TINY) == a
    b = numerics("Pendulum-v1", 100, 2, **TINY)
    assert all(a[s]["digest"] != b[s]["digest"] for s in a)
    assert a["paper"]["digest"] != a["equal-data"]["digest"]
