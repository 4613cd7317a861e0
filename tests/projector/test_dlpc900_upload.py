"""Driver uploads: two-controller DMDs get each image in halves; an upload is one exchange."""

from __future__ import annotations

import struct
import threading
import time

import numpy as np
import pytest

from drivers.dlpc900 import DLPC900, DLPC900Error
from firmware_mocks.dlpc900_usb import usb_emulation

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def dual(clock):
    with usb_emulation(clock=clock, dmd_type=2) as emu:
        yield emu


def _loads(model, opcode: int) -> list[tuple[int, int]]:
    """(image index, header width) of every load init `opcode` and the image it announced."""
    out = []
    log = list(model.command_log)
    for i, c in enumerate(log):
        if c.opcode == opcode:
            first = next(d for d in log[i + 1:] if d.opcode == opcode + 1)
            out.append((struct.unpack_from("<H", c.data)[0], struct.unpack_from("<H", first.data, 2 + 4)[0]))
    return out


def test_dual_controller_images_are_split_column_wise(dual, clock, gray):
    dual.model.width, dual.model.height = 64, 8
    cols, rows = gray(64, 8), gray(64, 8, vertical=False)
    with DLPC900.open(sleep=clock.sleep) as dlp:
        assert dlp.dual_controller()
        pairs = dlp.upload_patterns([cols, rows], exposure_us=5000, start=True)
        assert len(pairs) == 2 and all(left.width == right.width == 32 for left, right in pairs)
        both = np.concatenate([cols, rows])
        for k in range(len(both)):
            assert np.array_equal(dual.model.dmd_pattern(k).astype(bool), both[k]), k
        assert dual.model.sequencer == "running"
    # each image index went to both controllers, in reverse order, with a half-width header
    assert _loads(dual.model, 0x1A2A) == [(1, 32), (0, 32)]
    assert _loads(dual.model, 0x1A2C) == [(1, 32), (0, 32)]


def test_dual_controller_full_resolution_gray_codes(dual, clock, gray):
    with DLPC900.open(sleep=clock.sleep) as dlp:
        pats = gray(2560, 1600)
        ((left, right),) = dlp.upload_patterns(pats, exposure_us=5000, start=True)
        assert (left.width, right.width, left.height) == (1280, 1280, 1600)
        for k in range(len(pats)):
            assert np.array_equal(dual.model.dmd_pattern(k).astype(bool), pats[k]), k


def test_dual_controller_needs_an_even_width(dual, clock):
    dual.model.width, dual.model.height = 16, 2
    with DLPC900.open(sleep=clock.sleep) as dlp:
        with pytest.raises(ValueError, match="even width"):
            dlp.upload_patterns(np.ones((1, 2, 15), bool), exposure_us=500)


def test_single_controller_uses_the_primary_loads_only(dlp, emu):
    emu.model.width, emu.model.height = 16, 2
    assert not dlp.dual_controller()
    (image,) = dlp.upload_patterns(np.ones((3, 2, 16), bool), exposure_us=500)
    assert image.width == 16
    assert not any(c.opcode in (0x1A2C, 0x1A2D) for c in emu.model.command_log)


def _slow_chunks(emu, pause_s: float = 0.002):
    """Let other threads run while each image chunk arrives (the GIL otherwise favours one)."""
    receive = emu.receive

    def slowly(report: bytes) -> None:
        if report[4:6] in (b"\x2b\x1a", b"\x2d\x1a"):
            time.sleep(pause_s)
        receive(report)

    emu.receive = slowly


def test_a_status_poller_cannot_interleave_with_an_upload(dlp, emu):
    emu.model.width, emu.model.height = 64, 8
    pats = np.random.default_rng(0).random((30, 8, 64)) < 0.5  # 2 raw images of 4 chunks each
    _slow_chunks(emu)
    stop, errors, polls = threading.Event(), [], []

    def poll() -> None:
        while not stop.is_set():
            try:
                dlp.system_status()  # 0x1A0B: a command the upload itself never sends
                polls.append(time.monotonic())
            except Exception as exc:  # pragma: no cover - reported below
                errors.append(exc)
                return

    poller = threading.Thread(target=poll)
    poller.start()
    try:
        while not polls:
            time.sleep(0.001)
        first = len(emu.model.command_log)
        dlp.upload_patterns(pats, exposure_us=105)
        log = list(emu.model.command_log)[first:]
    finally:
        stop.set()
        poller.join(10)
    assert not errors and len(polls) >= 1
    ops = [c.opcode for c in log]
    upload = [i for i, op in enumerate(ops) if op != 0x1A0B]
    inside = ops[upload[0]:upload[-1] + 1]
    assert 0x1A0B not in inside, "a status poll landed inside the upload"
    assert ops.count(0x1A2A) == 2 and inside[-1] == 0x0100  # the last image's error read ends it
    for k in range(30):
        assert np.array_equal(emu.model.dmd_pattern(k).astype(bool), pats[k])


def test_blank_from_another_thread_stops_an_upload_at_the_next_chunk(dlp, emu):
    emu.model.width, emu.model.height = 64, 32
    pats = np.random.default_rng(1).random((24, 32, 64)) < 0.5  # one raw image, 13 chunks
    chunks = []
    receive = emu.receive

    def hold_third_chunk(report: bytes) -> None:
        if report[4:6] == b"\x2b\x1a":
            chunks.append(report)
            if len(chunks) == 3:
                assert dlp._abort_upload.wait(10)  # blank() has asked; the upload must now yield
        receive(report)

    emu.receive = hold_third_chunk
    outcome = []

    def upload() -> None:
        try:
            dlp.upload_patterns(pats, exposure_us=105, start=True)
            outcome.append("finished")
        except DLPC900Error as exc:
            outcome.append(exc)

    t = threading.Thread(target=upload)
    t.start()
    while len(chunks) < 3:
        time.sleep(0.001)
    report = dlp.blank()
    t.join(10)
    assert report.method == "idle" and emu.model.dark
    assert len(outcome) == 1 and "blank() was called" in str(outcome[0])
    assert len(chunks) == 3 and emu.model.sequencer == "stopped" and 0 not in emu.model.images
