"""Shared checks of the lfd tests."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest


def _single_matches_batch(policy, observations, starts):
    """One observation at a time (the n = 1 fast path) gives what a batch of two identical
    environments (the vectorised path) gives: actions, fused increments and the whole state."""
    single = batch = None
    for o, first in zip(observations, starts, strict=True):
        d1 = policy.predict_distribution(o, state=single, episode_start=np.array([first]))
        single = policy._memory if single is None else single
        d2 = policy.predict_distribution(
            np.stack([o, o]), state=batch, episode_start=np.array([first, first])
        )
        batch = policy._memory if batch is None else batch
        np.testing.assert_array_equal(d1.action[0], d2.action[0])
        np.testing.assert_allclose(d1.joint_increment[0], d2.joint_increment[0], atol=1e-12)
        np.testing.assert_allclose(d1.phase[0], d2.phase[0], atol=1e-12)
        for name in ("clock", "last_time", "waited", "fresh"):
            np.testing.assert_allclose(getattr(single, name)[0], getattr(batch, name)[0])
        for name in ("seen", "reached", "position", "variance", "rotation", "outliers"):
            a, b = getattr(single, name), getattr(batch, name)
            assert a.keys() == b.keys()
            for key in a:
                np.testing.assert_allclose(a[key][0], b[key][0], atol=1e-12)


@pytest.fixture
def single_matches_batch() -> Callable[..., Any]:
    """The check above, for the tests of both the coffee and the plain-array policies."""
    return _single_matches_batch
