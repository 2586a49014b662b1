"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def fmu_cache(tmp_path_factory):
    """A build cache of the test module's own: FMUs built from source land there, not in the user's."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DYNABRAIN_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


@pytest.fixture(scope="module", params=[True, False], ids=["compiled", "plain"])
def tick_runner(request):
    """Runs a test module twice: its worlds made without ``compiled=`` step with the generated tick,
    then with the plain loop (through ``DYNABRAIN_COMPILED``). Use it for a whole module with
    ``pytestmark = pytest.mark.usefixtures("tick_runner")``; the value is the ``compiled`` in force."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DYNABRAIN_COMPILED", "1" if request.param else "0")
        yield request.param
