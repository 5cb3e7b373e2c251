"""Fixtures for the whole suite."""

from __future__ import annotations

import os

import pytest

from testkit.helpers import LOG_DIR_ENV


@pytest.fixture(scope="session", autouse=True)
def process_logs(tmp_path_factory):
    """The logs of the processes the tests start go to this run's pytest temporary folder (``.../logs``): pytest keeps
    the last three runs' folders and removes older ones, so repeated runs do not fill the system's temporary folder."""
    before = os.environ.get(LOG_DIR_ENV)
    path = tmp_path_factory.mktemp("logs", numbered=False)
    os.environ[LOG_DIR_ENV] = str(path)
    yield path
    if before is None:
        os.environ.pop(LOG_DIR_ENV, None)
    else:
        os.environ[LOG_DIR_ENV] = before
