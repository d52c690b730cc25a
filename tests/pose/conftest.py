"""Fixtures of the pose tests."""

from __future__ import annotations

import pytest

from helpers.synthetic import make_population


@pytest.fixture(scope="session")
def pose_population():
    return make_population()
