"""Session-wide fixtures of the end-to-end tests (registered in conftest.py)."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def smoke_reference(tmp_path_factory):
    """One uninterrupted local run (process pool) of the smoke grid with the FAST settings, shared by every
    test module that compares against it (tests/test_e2e_workflow.py, tests/test_cluster.py)."""
    from tests.test_e2e_workflow import run_reference

    return run_reference(tmp_path_factory.mktemp("reference"))
