"""Shared fixtures."""

import numpy as np
import pytest
from helpers import random_cloud


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def cloud():
    return random_cloud(500)
