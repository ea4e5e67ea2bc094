"""Shared fixture of the sweep tests: one 2-worker LocalCluster."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def client():
    from cca_cli.stages.sweep import open_client

    with open_client(workers=2) as c:
        yield c
