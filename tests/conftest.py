"""Shared test fixtures: small random image sets; one itk-elastix worker."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)


@pytest.fixture
def small_images(rng) -> np.ndarray:
    """Ten smooth-ish 2D images (10, 12, 14): structure plus noise, generic rank."""
    base = rng.normal(size=(12, 14))
    return base + 0.5 * rng.normal(size=(10, 12, 14))


# ----------------------------------------------------------------------------- elastix

_ELASTIX: dict = {}  # the running worker, and the id of the last test that uses it


@pytest.fixture(scope="session")
def elastix_worker():
    """One running itk-elastix worker for every test module that takes one.

    Each new worker loads itk-elastix on its first job: about 10 s of CPU (and 1 GB) per
    module that started its own. Its jobs are independent requests served one at a time,
    as the demo's ~60 are. It is stopped after the last test that uses it (see
    pytest_runtest_teardown), not held until the end of the session.
    """
    from itk_nrreval.experiments.registration import ElastixWorker

    with ElastixWorker() as worker:
        _ELASTIX["worker"] = worker
        yield worker
    _ELASTIX.pop("worker", None)


@pytest.hookimpl(trylast=True)  # after deselection (-k, -m): the tests that will run
def pytest_collection_modifyitems(session, config, items):
    users = [item for item in items if "elastix_worker" in getattr(item, "fixturenames", ())]
    _ELASTIX["last"] = users[-1].nodeid if users else None


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    if item.nodeid == _ELASTIX.get("last") and "worker" in _ELASTIX:
        _ELASTIX.pop("worker").close()  # the session fixture's exit closes it again: no-op
