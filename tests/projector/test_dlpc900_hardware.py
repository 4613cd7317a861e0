"""Against a real DLPC900 on the USB bus; deselected unless run with -m hardware."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.hardware


def test_real_projector_identifies_and_blanks():
    from drivers.dlpc900 import DLPC900, DisplayMode, list_devices

    if not list_devices():
        pytest.skip("no DLPC900 (0451:c900) attached")
    with DLPC900.open() as dlp:
        fw = dlp.firmware_version()
        assert fw.application.major >= 1
        assert dlp.hardware_status().init_ok
        mode = dlp.display_mode()
        dlp.set_display_mode(DisplayMode.PATTERN_ON_THE_FLY)
        dlp.set_display_mode(mode)
        report = dlp.blank()
        assert report.method in ("idle", "leds off", "standby")
