"""cae_lcd.fleet.budget: the candidates a keyframe verifies over all other robots, against a brute-force selection."""

from __future__ import annotations

import numpy as np
import pytest

from cae_lcd.fleet.budget import shortlist


def brute(scores, k, min_score, budget):
    """Every (robot, position) in a robot's top-k above min_score, the best ``budget`` of them."""
    pool = sorted((-s[i], r, i) for r, s in scores.items() for i in np.argsort(-s, kind="stable")[:k]
                  if s[i] >= min_score)
    return sorted((r, int(i)) for _, r, i in (pool[:budget] if budget else pool))


@pytest.fixture
def scores():
    rng = np.random.default_rng(3)
    return {f"r{j:02d}": rng.uniform(-0.2, 1.0, size=int(rng.integers(0, 40))) for j in range(31)}


class TestShortlist:
    @pytest.mark.parametrize("k, min_score, budget", [(3, 0.0, 8), (3, 0.0, 0), (1, 0.5, 4), (5, -1.0, 1),
                                                      (3, 0.99, 8)])
    def test_matches_brute_force(self, scores, k, min_score, budget):
        chosen = shortlist(scores, k, min_score, budget)
        got = sorted((r, int(i)) for r, ids in chosen.items() for i in ids)
        assert got == brute(scores, k, min_score, budget)
        assert all(len(ids) <= k and len(ids) > 0 for ids in chosen.values())
        if budget:
            assert len(got) <= budget
        for r, ids in chosen.items():  # best first within a robot
            assert np.all(np.diff(scores[r][ids]) <= 0)

    def test_without_bound_every_robot_gets_its_top_k(self, scores):
        chosen = shortlist(scores, 3, -1.0, 0)
        assert set(chosen) == {r for r, s in scores.items() if len(s)}
        assert sum(map(len, chosen.values())) == sum(min(3, len(s)) for s in scores.values())

    def test_empty(self):
        assert shortlist({}, 3, 0.0, 8) == {} and shortlist({"a": np.zeros(0)}, 3, 0.0, 8) == {}
