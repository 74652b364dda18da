"""Shared fixtures."""

import numpy as np
import pytest
from helpers import build_extension_zip, random_cloud


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def cloud():
    return random_cloud(500)


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory):
    """The extension zip built by blender_ext.py, once for every test that installs it into Blender."""
    return build_extension_zip(tmp_path_factory.mktemp("extension"))
