"""The DLPC900 emulator in its own process, driven by the real driver through the socket
backend: the device keeps its state when a host process dies and loses that host's claim."""

from __future__ import annotations

import multiprocessing
import os
import signal

import pytest
import usb.core

from drivers.dlpc900 import DLPC900, DisplayMode
from dpmhw.tracking import wait_for
from firmware_mocks.dlpc900_socket import EmulatorProcess, SocketBackend, socket_usb

WAIT_S = 30  # for what must happen eventually: generous, as only broken code waits this long


@pytest.fixture
def emulator():
    em = EmulatorProcess.start("EMU0001", "EMU0002")
    yield em
    em.close()


def _light_and_die(address: str, key: bytes, ready) -> None:
    """A host process that lights the projector and is then killed before it can clean up."""
    with socket_usb(address, key):
        dlp = DLPC900.open("EMU0001", settle_s=0.0)
        if dlp.in_standby():
            dlp.wake()
        dlp.set_display_mode(DisplayMode.VIDEO)
        dlp.set_idle(False)
        ready.send("lit")
        ready.recv()  # until killed


def test_driver_speaks_to_the_emulator_process_and_reads_back(emulator):
    with socket_usb(emulator.address, emulator.authkey):
        found = sorted(usb.util.get_string(d, d.iSerialNumber)
                       for d in usb.core.find(find_all=True, idVendor=0x0451, idProduct=0xC900))
        assert found == ["EMU0001", "EMU0002"]
        dlp = DLPC900.open("EMU0002", settle_s=0.0)
        try:
            dlp.set_display_mode(DisplayMode.VIDEO)
            dlp.set_idle(False)
            assert not emulator.inspect()[1]["dark"] and emulator.inspect()[1]["claimed"]
            report = dlp.blank()
            assert report.method == "idle" and dlp.idle() is True
            state = {d["serial"]: d for d in emulator.inspect()}
            assert state["EMU0002"]["dark"] and state["EMU0002"]["idle"] and not state["EMU0001"]["idle"]
        finally:
            dlp.close()
        assert not emulator.inspect()[1]["claimed"]


def test_a_killed_host_leaves_the_device_as_it_was_and_another_can_idle_it(emulator):
    ctx = multiprocessing.get_context("spawn")
    ours, theirs = ctx.Pipe()
    host = ctx.Process(target=_light_and_die, args=(emulator.address, emulator.authkey, theirs), daemon=True)
    host.start()
    assert ours.poll(60) and ours.recv() == "lit"
    os.kill(host.pid, signal.SIGKILL)
    host.join(10)
    # the device outlived its host, still lit; the kernel (here: the emulator) dropped the claim
    assert wait_for(lambda: not emulator.inspect()[0]["claimed"], WAIT_S)
    assert not emulator.inspect()[0]["dark"]
    with socket_usb(emulator.address, emulator.authkey):
        dlp = DLPC900.open("EMU0001", settle_s=0.0)
        assert dlp.blank().method == "idle"
        dlp.close()
    assert emulator.inspect()[0]["dark"]


def test_a_gone_emulator_is_an_unplugged_device_and_a_wrong_key_is_refused(emulator):
    with pytest.raises(Exception, match="digest|authentication|AuthenticationError"):
        SocketBackend(emulator.address, b"wrong key 123456")._call("enumerate")
    backend = SocketBackend(emulator.address, emulator.authkey)
    assert backend._call("enumerate") == [0, 1]
    emulator.close()
    with pytest.raises(usb.core.USBError) as err:
        backend._call("enumerate")
    assert err.value.errno == 19  # ENODEV, as for a pulled cable
    assert list(backend.enumerate_devices()) == []
