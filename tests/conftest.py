"""Shared fixtures."""

import blender_session
import numpy as np
import pytest
from helpers import build_extension_zip, random_cloud


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(session, config, items):
    blender_session.blender_last(items)


def pytest_collection_finish(session):
    blender_session.start_workers(session.config, session.items)


def pytest_sessionfinish(session, exitstatus):
    blender_session.stop_workers()


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
