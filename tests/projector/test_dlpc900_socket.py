"""The DLPC900 emulator in its own process, driven by the real driver through the socket
backend: the device keeps its state when a host process dies and loses that host's claim."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pathlib
import shutil
import signal
import tempfile

import pytest
import usb.core

from dpmhw.session.testing import wait_for
from drivers.dlpc900 import DLPC900, DisplayMode
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


def test_silent_clients_do_not_hold_up_the_emulator_and_are_dropped_after_the_handshake_timeout(emulator):
    import socket
    import time

    from firmware_mocks.dlpc900_socket import HANDSHAKE_TIMEOUT_S

    silent = [socket.socket(socket.AF_UNIX) for _ in range(8)]
    try:
        for s in silent:
            s.connect(emulator.address)  # and never answer the challenge
        t0 = time.monotonic()
        assert emulator.inspect()[0]["serial"] == "EMU0001"  # served beside them
        # bound: the emulator answers without waiting out a silent handshake (2 s), with room for a loaded machine
        assert time.monotonic() - t0 < HANDSHAKE_TIMEOUT_S
        for s in silent:  # each was dropped after the handshake timeout: EOF, not a hang
            s.settimeout(WAIT_S)
            while s.recv(4096):  # the challenge, then EOF
                pass
    finally:
        for s in silent:
            s.close()


def test_oversized_and_malformed_requests_get_an_error_reply_and_the_connection_stays_usable(emulator):
    from firmware_mocks.dlpc900_socket import MAX_REQUEST_BYTES, _connect

    conn = _connect(emulator.address, emulator.authkey)
    try:
        conn.send(("open_device", (0,)))
        outcome, handle = conn.recv()
        assert outcome == "ok"
        for size in (256 << 20, -1, 65536):  # 256 MB would be allocated as asked; wLength is 16 bits
            conn.send(("ctrl_transfer", (handle, 0xC0, 0, 0, 0, size, 100)))
            assert conn.recv() == ("error", ("ValueError", f"ctrl_transfer: wLength must be an integer 0..65535, "
                                                           f"not {size!r}"))
        conn.send(("intr_read", (handle, 0x81, 0, 1 << 30, 100)))
        assert conn.recv()[1][1].startswith("intr_read: size must be an integer 0..65535")
        for bad in ("enumerate", ["enumerate", ()], ("enumerate",), (1, ()), ("enumerate", "x")):
            conn.send(bad)
            outcome, (kind, text) = conn.recv()
            assert outcome == "error" and kind == "ValueError" and "request: must be (operation: str" in text
        conn.send_bytes(b"not a pickle")
        assert conn.recv()[1][1].startswith("request: not a pickled")
        conn.send(("enumerate", ()))
        assert conn.recv() == ("ok", [0, 1])  # the same connection still works
        with contextlib.suppress(BrokenPipeError):  # longer than any request: refused unread, then closed
            conn.send_bytes(b"x" * (MAX_REQUEST_BYTES + 1))
        assert conn.recv() == ("error", ("ValueError", f"request: longer than {MAX_REQUEST_BYTES} bytes"))
        with pytest.raises(EOFError):
            conn.recv()
    finally:
        conn.close()
    assert emulator.inspect()[0]["serial"] == "EMU0001" and emulator.process.is_alive()


@pytest.fixture
def short_dir():
    """A folder whose socket paths fit an AF_UNIX address (pytest's tmp_path may not, under xdist)."""
    path = tempfile.mkdtemp(prefix="dpmhw-t")
    yield pathlib.Path(path)
    shutil.rmtree(path, ignore_errors=True)


def test_a_socket_path_too_long_for_a_unix_address_is_refused_at_once_by_name(tmp_path, monkeypatch):
    from firmware_mocks import dlpc900_socket as mod

    deep = tmp_path / ("d" * 120)
    deep.mkdir()
    monkeypatch.setattr(mod, "EMULATOR_DIRS", mod.OwnedNames(str(deep), "dpmhw-dlpc900"))
    with pytest.raises(RuntimeError, match="socket path .* over the 107 .* set TMPDIR"):
        EmulatorProcess.start(timeout_s=600)  # refused before a process starts: no wait
    assert list(deep.iterdir()) == []


def test_a_killed_owner_leaves_no_folder_and_stale_folders_are_swept(short_dir, monkeypatch):
    from firmware_mocks import dlpc900_socket as mod

    dirs = mod.OwnedNames(str(short_dir), "dpmhw-dlpc900")
    monkeypatch.setattr(mod, "EMULATOR_DIRS", dirs)
    dead = subprocess_pid_that_exited()
    stale = short_dir / f"dpmhw-dlpc900-{dead}-abc123"
    stale.mkdir()
    (stale / "usb.sock").write_bytes(b"")
    ours = short_dir / f"dpmhw-dlpc900-{os.getpid()}-def456"  # a live owner's: kept
    ours.mkdir()
    em = EmulatorProcess.start()
    try:
        assert not stale.exists() and ours.exists()
        assert os.path.dirname(em.address).startswith(str(short_dir / f"dpmhw-dlpc900-{os.getpid()}-"))
        em._conn.close()  # as when the owner dies: the emulator exits and removes its folder
        em.process.join(WAIT_S)
        assert not os.path.exists(os.path.dirname(em.address))
    finally:
        em.close()
    assert sorted(p.name for p in short_dir.iterdir()) == [ours.name]


def subprocess_pid_that_exited() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid
