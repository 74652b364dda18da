"""Shared fixtures, and CI's rule for skips."""

import os

import blender_session
import numpy as np
import pytest
from helpers import PLATFORM_SKIP, build_extension_zip, random_cloud


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(session, config, items):
    blender_session.blender_last(items)


def pytest_collection_finish(session):
    blender_session.start_workers(session.config, session.items)


def pytest_sessionfinish(session, exitstatus):
    blender_session.stop_workers()


# Skips for what a platform cannot do say so (helpers.skip_platform). Any other skip means a tool the
# suite needs is missing (a Python for a Blender version, node and npm, numba, a peer's package, a
# registry): on CI (CI set) that is a failure, so a fresh machine cannot pass by testing less.


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if not (os.environ.get("CI") and report.skipped and not hasattr(report, "wasxfail")):
        return
    reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    reason = reason.removeprefix("Skipped: ")
    if not reason.startswith(PLATFORM_SKIP):
        report.outcome = "failed"
        report.longrepr = f"skipped on CI, where every tool the tests need must be installed: {reason}"


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
