"""Shared test fixtures: small random image sets."""

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
