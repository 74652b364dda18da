"""Shared fixtures, and CI's rule for skips."""

import os

import blender_session
import numpy as np
import pytest
from helpers import PLATFORM_SKIP, build_extension_zips, random_cloud


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(session, config, items):
    blender_session.blender_last(items)


def pytest_collection_finish(session):
    blender_session.start_workers(session.config, session.items)


def pytest_sessionfinish(session, exitstatus):
    blender_session.stop_workers()


def pytest_terminal_summary(terminalreporter):
    for line in blender_session.worker_times():
        terminalreporter.write_line(line)


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
def platform_zips(tmp_path_factory):
    """Every platform's extension zip, built by Blender's split build as `./run package` builds them:
    {Blender platform: path}."""
    return build_extension_zips(tmp_path_factory.mktemp("extension"))


@pytest.fixture(scope="session")
def extension_zip(platform_zips):
    """The linux-x64 zip, the one every test installing the extension into Blender uses."""
    return platform_zips["linux-x64"]
