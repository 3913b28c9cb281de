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


def test_the_digest_of_ma_sac_differs_from_ma_td3s() -> None:
    sac = numerics("Pendulum-v1", 100, 1, algo="ma-sac", **TINY)
    assert sac == numerics("Pendulum-v1", 100, 1, algo="ma-sac", **TINY)
    assert all(sac[s]["digest"] != numerics("Pendulum-v1", 100, 1, **TINY)[s]["digest"] for s in sac)
