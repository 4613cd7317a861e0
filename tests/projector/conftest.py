"""Fixtures: an emulated DLPC900 on a fake clock and a driver talking to it over pyusb."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.dlpc900 import DLPC900
from firmware_mocks.dlpc900_usb import usb_emulation


class FakeClock:
    """Monotonic ns clock that only moves when the driver 'sleeps' (or a test advances it)."""

    def __init__(self) -> None:
        self.t = 1_000_000_000
        self.sleeps: list[float] = []

    def __call__(self) -> int:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.t += int(round(seconds * 1e9))

    def advance(self, ns: int) -> None:
        self.t += ns


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def emu(clock):
    with usb_emulation(clock=clock) as device:
        yield device


@pytest.fixture
def dlp(emu, clock):
    d = DLPC900.open(sleep=clock.sleep, timeout_ms=200, reconnect_backoff_s=0.05)
    yield d
    d.close()


@pytest.fixture
def gray():
    return gray_codes


def gray_codes(width: int, height: int, vertical: bool = True) -> np.ndarray:
    """(n, H, W) bool Gray-code stripes, as structured-light calibration shows them."""
    n = int(np.ceil(np.log2(width if vertical else height)))
    x = np.arange(width if vertical else height)
    g = x ^ (x >> 1)
    bits = ((g[None, :] >> np.arange(n)[::-1, None]) & 1).astype(bool)  # MSB first
    if vertical:
        return np.broadcast_to(bits[:, None, :], (n, height, width)).copy()
    return np.broadcast_to(bits[:, :, None], (n, height, width)).copy()
