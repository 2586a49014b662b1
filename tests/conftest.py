"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def fmu_cache(tmp_path_factory):
    """A build cache of the test module's own: FMUs built from source land there, not in the user's."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DYNABRAIN_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield
