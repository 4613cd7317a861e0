"""Against real trackers: run with `-m hardware` and the device named in the environment.

DPMHW_MOTIVE_SERVER=192.168.1.10 DPMHW_LOCAL_INTERFACE=192.168.1.20 pytest -m hardware tests/trackers
DPMHW_POLHEMUS_PORT=/dev/ttyUSB0 pytest -m hardware tests/trackers
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from dpmhw.session.testing import wait_for
from dpmhw.tracking import TrackerState

pytestmark = pytest.mark.hardware


def _check_live_samples(tracker) -> None:
    assert wait_for(lambda: tracker.status().frames >= 50, 15), tracker.status()
    assert tracker.status().state == TrackerState.STREAMING
    now = time.monotonic_ns()
    for sample in tracker.latest_all().values():
        # stamped in the recent past on this host's clock, arriving after it describes
        assert 0 <= now - sample.t_exposure_ns < 1e9 and sample.latency_ns >= 0
        if sample.valid:
            assert np.isfinite(sample.translation).all() and np.linalg.norm(sample.translation) < 100


def test_real_motive():
    server = os.environ.get("DPMHW_MOTIVE_SERVER")
    if not server:
        pytest.skip("set DPMHW_MOTIVE_SERVER to Motive's address")
    from drivers.natnet import NatNetClient

    with NatNetClient(server, local_interface=os.environ.get("DPMHW_LOCAL_INTERFACE", "0.0.0.0")) as client:
        _check_live_samples(client)
        assert client.clock.method == "round-trip"


def test_real_polhemus():
    port = os.environ.get("DPMHW_POLHEMUS_PORT")
    if not port:
        pytest.skip("set DPMHW_POLHEMUS_PORT to the tracker's serial port")
    from drivers.serial_tracker import PolhemusTracker

    with PolhemusTracker(port) as tracker:
        _check_live_samples(tracker)
        assert tracker.model in ("Liberty", "Patriot", "Latus")
