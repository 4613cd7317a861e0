"""Suite-wide settings: property tests are judged on what the code returns, never on how fast a
loaded machine ran one example (hypothesis's 200-ms deadline and its too-slow health check are
wall-clock checks; a CPU hog beside the suite tripped neither only by luck)."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("dpmhw", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("dpmhw")


@pytest.fixture(autouse=True, scope="session")
def _own_runtime_dir(tmp_path_factory):
    """Session lock files (dpmhw.session.instance) in a directory of this run's own, so a suite
    run beside another one's mock sessions sees no 'another --mock session' warning."""
    os.environ["DPMHW_RUNTIME_DIR"] = str(tmp_path_factory.mktemp("runtime"))
