"""Per-run scores (mam_lab/scores.py): the best live score, the evaluation grid, the 50 apple."""

from __future__ import annotations

import numpy as np
import pytest

from mam_lab.analysis import SUCCESS_RETURN
from mam_lab.scores import best_live_score, bucket_points, first_reach, last_n_mean


def test_best_live_score_and_buckets():
    assert best_live_score({"mean": [3.0, 7.0, None]}) == 7.0
    assert best_live_score({"mean": [None, 5.0]}) == 5.0
    assert best_live_score({"mean": [None, None]}) is None
    assert best_live_score({"returns": [[1.0, 3.0], []]}) == 2.0
    # floor to the grid; the last evaluation of a cell wins (a late round and the final evaluation)
    cells = bucket_points([(50, 1.0), (100, 2.0), (130, 3.0), (1003, 4.0), (1000, 9.0), (1005, 5.0)], 100)
    assert cells == {0: 1.0, 100: 3.0, 1000: 5.0}
    pts = [(s, float(s // 100)) for s in range(100, 2001, 100)]
    assert last_n_mean(pts, 100) == pytest.approx(np.mean(range(11, 21)))
    assert last_n_mean(pts[:3], 100) == pytest.approx(2.0)
    assert np.isnan(last_n_mean([], 100))



def test_fifty_apple_bound_and_first_reach():
    # a 50 apple reached at the last of the 100 steps: 50 − 100·0.01 = 49; the best 10 apple: 9.99
    assert 48.99 < SUCCESS_RETURN <= 49.0 and 50 + 100 * -0.01 >= SUCCESS_RETURN
    triples = [(100, 33.0, 9.97), (200, 66.0, 49.96), (300, None, 9.97), (400, 133.0, 49.9)]
    assert first_reach(triples, SUCCESS_RETURN) == (200, 66.0)
    assert first_reach(triples[:1], SUCCESS_RETURN) is None

