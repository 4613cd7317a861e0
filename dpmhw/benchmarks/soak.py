"""Soak test: a mock session (the real tracker driver against its emulator — Motive over NatNet,
or a Polhemus-style tracker on a pty —, the emulated DLPC900 over pyusb, the real loop) with faults
injected one at a time at random moments, for `minutes`.

Fault kinds, each injected only while the session is projecting. NatNet (`NATNET_KINDS`):

    tracker_stall        the NatNet server sends nothing for 0.3–1.5 s
    tracker_restart      Motive quits; 0.2–1 s later it runs again on the same ports (the mock's
                         `restart`: frame numbers and clock begin again, unicast clients forgotten)
    corrupt_datagrams    for 1–3 s, 30 % of the frames are truncated or have bytes flipped
    foreign_datagrams    for 1–3 s, another address (127.0.0.2) sends frames at 360 Hz with a pose
                         1 km away and frame numbers 10⁶ ahead

Serial (`SERIAL_KINDS`):

    serial_stall         the device leaves continuous mode (as on a stray `P`): nothing more until
                         the driver asks again
    serial_noise         for 1–3 s, 15 % garbage bytes between records and 15 % corrupted records
    serial_unplug        the device disappears (its pty and its stable name go) for 0.5–2 s, then is
                         replugged: powered up afresh on a new pty behind the same name, as udev's
                         by-id name follows a replugged adapter; the driver sees the name come back,
                         reconnects and re-initialises it (incl. the 2-s reset wait real units need)

Either tracker (`COMMON_KINDS`):

    implausible_sample   one or two genuine frames carry a pose 2 m away (inside the workspace:
                         caught by the speed limit) or 1 km away (outside it): the tracker mock's
                         `pose_offset_m` (a mis-solve; the world's truth is unchanged)
    implausible_burst    genuine frames carry a pose 50 m away (outside the workspace) for 0.2–1 s
                         (a sustained offset *inside* the workspace is, by design, accepted once
                         it is reachable at `max_speed_m_s`: kinematics cannot tell it from a move)
    usb_stall            the projector's next 3 USB transfers fail (halted endpoint)
    usb_unplug           the projector is unplugged for 0.5–2 s, then replugged (power-cycled)
    api_load             for 3 s, two clients hammer the API process with hostile requests (NaN,
                         wrong types, oversized bodies, bad tokens) and status reads

Every fault goes in through a fault surface of the mock it concerns (the NatNet server's
`stall`, `restart`, corruption probabilities and `pose_offset_m`; the Polhemus emulator's
`pause_streaming`, noise probabilities, `pose_offset_m`, `unplug`/`replug`; the DLPC900's `stall`,
`unplug`/`replug`), or from outside (foreign datagrams, API clients), so the real drivers meet
real faults. The soak's wrappers around the sink and the recorder only observe.

What is measured comes from stamps the session's own code recorded, seen through public
surfaces: every present (the sink's return value), the lit ones (the records the loop hands its
recorder — the recording's rows), the tracker's published samples (its callback: arrival and
exposure stamps; the soak keeps only the gaps), and the safety monitor's transitions. Per fault:

- time to dark: injection → the first black frame; and the newest good sample's exposure → that
  frame (the stale rule counts from the exposure: goal `stale_after_ms` + one frame);
- when the tracker's samples stopped, the first good sample after the gap, the safety cause's
  clear and the first lit frame: good sample → lit frame is the resume time the goal bounds
  (`holdoff_s` + one frame); fault's end → good sample is the device's or reconnect's part;
- one frame: the median interval between lit presents in the second before the fault (the run's
  median when that second had fewer than 3);
- lit frames presented while a safety cause was active (must be 0), and lit frames whose pose was
  more than 0.5 m from the truth (the implausible ones; must be 0);
- the API answers with status ≥ 500 (must be 0).

At the end: recording rows (frames.csv) against lit frames presented, and the process RSS at start
and end.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import random
import shutil
import socket
import tempfile
import threading
import time
import urllib.error
import urllib.request
from array import array
from pathlib import Path
from typing import Callable

import numpy as np

from dpmhw.session.config import load_session_config
from dpmhw.session.testing import wait_for

__all__ = ["FAULT_KINDS", "KINDS_BY_TRACKER", "format_table", "plot_soak", "run_soak"]

log = logging.getLogger(__name__)

NATNET_KINDS = ("tracker_stall", "tracker_restart", "corrupt_datagrams", "foreign_datagrams")
SERIAL_KINDS = ("serial_stall", "serial_noise", "serial_unplug")
COMMON_KINDS = ("implausible_sample", "implausible_burst", "usb_stall", "usb_unplug", "api_load")
FAULT_KINDS = NATNET_KINDS + SERIAL_KINDS + COMMON_KINDS
KINDS_BY_TRACKER = {"natnet": NATNET_KINDS + COMMON_KINDS, "serial": SERIAL_KINDS + COMMON_KINDS}
# faults that stop good samples: the goal bounds their dark and resume times
TRACKER_KINDS = ("tracker_stall", "tracker_restart", "serial_stall", "serial_unplug", "implausible_burst")
_WRONG_POSE_M = 0.5  # a lit frame whose pose is this far from the truth showed an implausible pose
ATTRIBUTE_S = 1.0  # a dark spell starting later than this after a fault's end is not that fault's


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


class _PresentLog:
    """Wraps the session's sink: the time of every present (lit or black), as `present` returned it."""

    def __init__(self, sink):
        self.sink = sink
        self.t = array("q")
        self._lock = threading.Lock()

    def present(self, frame, t_target_ns: int) -> int:
        t = self.sink.present(frame, t_target_ns)
        with self._lock:
            self.t.append(t)
        return t

    def __getattr__(self, name):
        return getattr(self.sink, name)

    def snapshot(self) -> np.ndarray:
        with self._lock:
            return np.frombuffer(self.t, np.int64).copy()


class _TruthCheck:
    """Wraps the recorder, which the loop hands every lit frame it presented (and nothing else):
    logs their present times, and compares each frame's measured pose with the world's true pose
    at the sample's instant (the world's trajectories: the mocks' pose offsets never touch them)."""

    def __init__(self, recorder, truths: dict[int, Callable], epoch_s: float):
        self.recorder = recorder
        self.truths = truths
        self.epoch_s = epoch_s
        self.lit_t = array("q")
        self.wrong: list[tuple[int, float]] = []  # (t_present_ns, metres off)

    def lit_since(self, t_ns: int) -> bool:
        """A lit frame was presented after `t_ns` (read on another thread: one int, no lock needed)."""
        return len(self.lit_t) > 0 and self.lit_t[-1] > t_ns

    def frame(self, record, image) -> None:
        self.lit_t.append(record.t_present_ns)
        for body, pose in record.measured.items():
            t_s = record.sample_t_ns[body] / 1e9 - self.epoch_s
            _, truth = self.truths[body](t_s)
            off = float(np.linalg.norm(np.asarray(pose.t) - truth))
            if off > _WRONG_POSE_M:
                self.wrong.append((record.t_present_ns, off))
        if self.recorder is not None:
            self.recorder.frame(record, image)

    def __getattr__(self, name):
        return getattr(self.recorder, name)


class _SampleGaps:
    """A tracker callback (the public `add_callback`): per body, every gap between consecutive
    good samples longer than `min_gap_ns`, as (last arrival, its exposure, next arrival). Good:
    published (past the plausibility gate, so a dropped burst is a gap too), valid, and no older
    than `stale_ns` when it arrived (one stamped older cannot end a stale spell). Bounded: gaps
    only, a few per fault."""

    def __init__(self, min_gap_ns: int, stale_ns: int):
        self.min_gap_ns = min_gap_ns
        self.stale_ns = stale_ns
        self._last: dict[int, tuple[int, int]] = {}
        self.gaps: dict[int, list[tuple[int, int, int]]] = collections.defaultdict(list)
        self._lock = threading.Lock()

    def __call__(self, sample) -> None:
        if not sample.valid or sample.t_arrival_ns - sample.t_exposure_ns > self.stale_ns:
            return
        with self._lock:
            last = self._last.get(sample.rigid_body_id)
            if last is not None and sample.t_arrival_ns - last[0] > self.min_gap_ns:
                self.gaps[sample.rigid_body_id].append((last[0], last[1], sample.t_arrival_ns))
            self._last[sample.rigid_body_id] = (sample.t_arrival_ns, sample.t_exposure_ns)

    def snapshot(self) -> dict[int, np.ndarray]:
        with self._lock:
            return {body: np.array(g, np.int64).reshape(-1, 3) for body, g in self.gaps.items()}


@dataclasses.dataclass
class _Fault:
    kind: str
    t_inject_ns: int
    t_clear_ns: int = 0
    detail: str = ""
    api_requests: int = 0
    api_5xx: int = 0


class _Injector:
    """Injects each fault kind into the mock rig of a running session."""

    def __init__(self, loop, rng: random.Random, token: str):
        self.loop = loop
        self.rng = rng
        self.rig = loop.parts.mock
        self.tracker = loop.parts.tracker
        self.token = token
        self.api = None

    @property
    def server(self):
        return self.rig.natnet

    def _natnet_module(self):
        import importlib

        return importlib.import_module(type(self.server).__module__)  # the mock's own encoder

    def inject(self, kind: str) -> _Fault:
        fault = _Fault(kind, time.monotonic_ns())
        try:
            getattr(self, kind)(fault)
        except Exception as exc:  # one failed injection is reported, not the end of a long soak
            log.exception("soak: injecting %s failed", kind)
            fault.detail = f"injection failed: {type(exc).__name__}: {exc}"
        if not fault.t_clear_ns:
            fault.t_clear_ns = time.monotonic_ns()
        return fault

    # -- tracker ------------------------------------------------------------------------------
    def tracker_stall(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(0.3, 1.5)
        fault.detail = f"{seconds:.2f} s"
        self.server.stall(seconds)
        time.sleep(seconds)
        fault.t_clear_ns = time.monotonic_ns()

    def tracker_restart(self, fault: _Fault) -> None:
        down = self.rng.uniform(0.2, 1.0)
        self.server.restart(down, server_uptime_s=self.rng.uniform(10.0, 1e5))  # the mock's fault surface
        fault.t_clear_ns = time.monotonic_ns()
        fault.detail = f"down {down:.2f} s"

    def corrupt_datagrams(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(1.0, 3.0)
        cfg = self.server.config
        before = sum(self.server.faults.values())
        cfg.truncate_prob = cfg.corrupt_prob = 0.15
        time.sleep(seconds)
        cfg.truncate_prob = cfg.corrupt_prob = 0.0
        fault.detail = f"{sum(self.server.faults.values()) - before} bad frames in {seconds:.1f} s"
        fault.t_clear_ns = time.monotonic_ns()

    def foreign_datagrams(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(1.0, 3.0)
        mod = self._natnet_module()
        target = self.tracker.local_address
        bodies = list(self.rig.world.objects)
        sent = 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind(("127.0.0.2", 0))
            end = time.monotonic() + seconds
            base = self.rng.randrange(10**6, 10**7)
            while time.monotonic() < end and target is not None:
                content = mod.FrameContent(
                    frame_number=base + sent, stamp_mid_exposure=1, stamp_transmit=2,
                    rigid_bodies=[(b, (1000.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, 1) for b in bodies])
                sock.sendto(mod.encode_frame(content, self.server.config.version), target)
                sent += 1
                time.sleep(1 / 360)
        fault.detail = f"{sent} datagrams"
        fault.t_clear_ns = time.monotonic_ns()

    def _glitch(self, offset, until: Callable[[], bool]) -> None:
        """Poses off the truth by `offset` until `until()`: the tracker mock's own fault surface."""
        mock = self.server if self.server is not None else self.rig.serial
        mock.pose_offset_m = np.asarray(offset, float)
        try:
            wait_for(until, 5.0, poll_s=0.0005)
        finally:
            mock.pose_offset_m = np.zeros(3)

    def _frames_sent(self) -> int:
        return self.server.frames_sent if self.server is not None else self.rig.serial.records_sent

    def implausible_sample(self, fault: _Fault) -> None:
        sent = self._frames_sent()
        metres = self.rng.choice([2.0, 1000.0])
        # NatNet: the mock encodes each frame one period ahead, so two frames sent means one
        # glitched; serial: one record per station per period, sampled when sent
        more = 1 if self.server is not None else len(self.rig.world.objects)
        self._glitch((metres, 0.0, 0.0), lambda: self._frames_sent() > sent + more)
        fault.detail = f"{self._frames_sent() - sent} frame(s) {metres:g} m off"
        fault.t_clear_ns = time.monotonic_ns()

    def implausible_burst(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(0.2, 1.0)
        end = time.monotonic() + seconds
        self._glitch((50.0, 0.0, 0.0), lambda: time.monotonic() >= end)
        fault.detail = f"{seconds:.2f} s 50 m off"
        fault.t_clear_ns = time.monotonic_ns()

    # -- serial tracker ---------------------------------------------------------------------------
    def serial_stall(self, fault: _Fault) -> None:
        self.rig.serial.pause_streaming()  # the device is silent until the driver asks again
        fault.detail = "left continuous mode"

    def serial_noise(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(1.0, 3.0)
        emu = self.rig.serial
        before = emu.records_corrupted, emu.garbage_bytes
        emu.garbage_prob = emu.corrupt_prob = 0.15
        time.sleep(seconds)
        emu.garbage_prob = emu.corrupt_prob = 0.0
        fault.detail = (f"{emu.records_corrupted - before[0]} corrupt records, {emu.garbage_bytes - before[1]} "
                        f"garbage bytes in {seconds:.1f} s")
        fault.t_clear_ns = time.monotonic_ns()

    def serial_unplug(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(0.5, 2.0)
        self.rig.serial.unplug()  # the mock's fault surface: the pty and its name are gone
        time.sleep(seconds)
        self.rig.serial.replug(device_uptime_s=self.rng.uniform(0.5, 1e5))  # same name, a fresh device
        fault.detail = f"gone {seconds:.2f} s"
        fault.t_clear_ns = time.monotonic_ns()

    # -- projector ------------------------------------------------------------------------------
    def usb_stall(self, fault: _Fault) -> None:
        self.rig.projector.stall(3)
        fault.detail = "3 transfers"

    def usb_unplug(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(0.5, 2.0)
        self.rig.projector.unplug()
        time.sleep(seconds)
        self.rig.projector.replug()
        fault.detail = f"{seconds:.2f} s"
        fault.t_clear_ns = time.monotonic_ns()

    # -- API ------------------------------------------------------------------------------------
    def api_load(self, fault: _Fault) -> None:
        if self.api is None:
            from server.process import ApiProcess

            self.api = ApiProcess(host="127.0.0.1", port=0, token=self.token).start(self.loop)
        base = f"http://127.0.0.1:{self.api.port}"
        bodies = [b'{"alpha": NaN}', b'{"alpha": Infinity}', b'{"alpha": "0.5"}', b'{"split_screen": "yes"}',
                  b'{"spp": true}', b'{"alpha": ' + b"9" * 40_000 + b"}", b'{"alpha": 0.2}']
        counts = [0, 0]
        codes: collections.Counter[int] = collections.Counter()
        lock = threading.Lock()
        end = time.monotonic() + 3.0

        def client(seed: int) -> None:
            rng = random.Random(seed)
            while time.monotonic() < end:
                if rng.random() < 0.3:
                    req = urllib.request.Request(f"{base}/status")
                else:
                    token = rng.choice([self.token, self.token, "wrong", ""])
                    headers = {"Content-Type": "application/json"}
                    if token:
                        headers["Authorization"] = f"Bearer {token}"
                    req = urllib.request.Request(f"{base}/settings", data=rng.choice(bodies), method="PATCH",
                                                 headers=headers)
                try:
                    with urllib.request.urlopen(req, timeout=5) as r:
                        code = r.status
                except urllib.error.HTTPError as exc:
                    code = exc.code
                except OSError:
                    code = 599  # no answer at all counts as a failure
                with lock:
                    counts[0] += 1
                    counts[1] += code >= 500
                    codes[code] += 1

        threads = [threading.Thread(target=client, args=(self.rng.randrange(2**31),), daemon=True) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(10)
        fault.api_requests, fault.api_5xx = counts
        fault.detail = f"{counts[0]} requests; status codes {dict(sorted(codes.items()))} (599: no answer in 5 s)"
        fault.t_clear_ns = time.monotonic_ns()

    def close(self) -> None:
        if self.api is not None:
            self.api.close()


def _cause_intervals(transitions, t_end_ns: int) -> list[tuple[int, int, str]]:
    """(start, end, name) of every period a cause was active."""
    open_since: dict[str, int] = {}
    out = []
    for tr in transitions:
        if tr.active:
            open_since.setdefault(tr.name, tr.t_ns)
        elif tr.name in open_since:
            out.append((open_since.pop(tr.name), tr.t_ns, tr.name))
    out += [(t0, t_end_ns, name) for name, t0 in open_since.items()]
    return out


def _lit_inside(t: np.ndarray, lit: np.ndarray, intervals) -> np.ndarray:
    """Mask of lit presents that happened while any interval was open (ends exclusive)."""
    inside = np.zeros(len(t), bool)
    for t0, t1, _ in intervals:
        inside |= (t > t0) & (t < t1)
    return inside & lit


def run_soak(minutes: float, *, seed: int = 0, tracker: str = "natnet", kinds: tuple[str, ...] | None = None,
             gap_s: tuple[float, float] = (1.5, 4.0), width: int = 128, height: int = 96,
             overrides: tuple[str, ...] = (), progress: Callable[[str], None] | None = None) -> dict:
    """Run the soak; returns {"config": …, "faults": [per fault], "summary": [per kind], "totals": …}.

    `width`×`height` is the projector's native size (the loop renders at its shading scale)."""
    from dpmhw.session.factory import build_session

    if tracker not in KINDS_BY_TRACKER:
        raise ValueError(f"tracker must be one of {', '.join(KINDS_BY_TRACKER)}, not {tracker!r}")
    kinds = KINDS_BY_TRACKER[tracker] if kinds is None else tuple(kinds)
    wrong = sorted(set(kinds) - set(KINDS_BY_TRACKER[tracker]))
    if wrong:
        raise ValueError(f"fault kinds {wrong} do not apply to the {tracker} tracker; its kinds: "
                         f"{', '.join(KINDS_BY_TRACKER[tracker])}")
    rng = random.Random(seed)
    token = "soak-token"
    rec_dir = Path(tempfile.mkdtemp(prefix="dpmhw-soak-"))
    cfg = load_session_config(overrides=[
        f"render.width={width}", f"render.height={height}", "sink.kind=recording", "api.enabled=false",
        "recording.enabled=true", f"recording.path={rec_dir}", f"api.token={token}", f"tracker.kind={tracker}",
        *overrides])
    loop = build_session(cfg, mock=True)
    world = loop.parts.mock.world
    truths = {body: obj.trajectory.pose for body, obj in world.objects.items()}
    present_log = _PresentLog(loop.parts.sink)
    loop.parts.sink = present_log
    truth_check = _TruthCheck(loop.parts.recorder, truths, world.epoch_s)
    loop.parts.recorder = truth_check
    gaps = _SampleGaps(int(cfg.safety.stale_after_ms * 1e6 / 4), int(cfg.safety.stale_after_ms * 1e6))
    loop.parts.tracker.add_callback(gaps)
    injector = _Injector(loop, rng, token)
    faults: list[_Fault] = []
    transitions: list = []
    say = progress or (lambda msg: log.info("%s", msg))

    def collect_transitions() -> None:  # the monitor keeps only the newest 4096: read as we go
        transitions.extend(loop.safety.transitions(transitions[-1].seq + 1 if transitions else 0))
    try:
        loop.start()
        if not wait_for(lambda: loop.status()["state"] == "running", 120):
            raise RuntimeError(f"soak: the session did not start: {loop.status()['reason']}")
        time.sleep(1.0)
        rss_start = _rss_mb()
        t_start = time.monotonic()
        t_end = t_start + minutes * 60
        next_report = t_start + 30
        recent_ns = max(int(cfg.safety.holdoff_s * 1e9), 100_000_000)
        while time.monotonic() < t_end:
            # each fault's dark and resume must be its own: wait until the session has lit a frame
            # since the last fault ended, then 1.5–4 s of projecting (so the frame interval before the
            # fault is measured), and inject only into a projecting session. "running" alone turns
            # true as the hold-off ends, a frame before the first lit present: a fault injected then
            # pre-empted the resume, and its clear was counted as the previous fault's
            since = faults[-1].t_clear_ns if faults else 0
            if not wait_for(lambda since=since: truth_check.lit_since(since), 30):
                say(f"soak: no lit frame 30 s after the last fault: {loop.status()['reason']}")
            time.sleep(rng.uniform(*gap_s))
            # lit within the last hold-off: not merely "running" at the end of an unexplained spell's
            # hold-off, before its first lit frame (the last lit one is then over a hold-off old)
            if not wait_for(lambda: loop.status()["state"] == "running"
                            and truth_check.lit_since(time.monotonic_ns() - recent_ns), 30):
                say(f"soak: not running 30 s after the last fault: {loop.status()['reason']}")
                continue
            kind = rng.choice(kinds)
            faults.append(injector.inject(kind))
            collect_transitions()
            if time.monotonic() >= next_report:
                next_report += 30
                say(f"soak: {(time.monotonic() - t_start) / 60:.1f}/{minutes:g} min, {len(faults)} faults, "
                    f"{loop.status()['frame_number']} frames, RSS {_rss_mb():.0f} MB")
        wait_for(lambda: loop.status()["state"] == "running", 30)
        time.sleep(1.0)
        rss_end = _rss_mb()
        collect_transitions()
        tracker_status = loop.parts.tracker.status()
    finally:
        injector.close()
        loop.stop()
    frames_presented = loop.status()["frame_number"]  # final: published by stop()
    # the recorder flushed and closed with the loop: count its rows now
    rows = sum(max(0, sum(1 for _ in open(p)) - 1) for p in rec_dir.glob("*/frames.csv"))
    shutil.rmtree(rec_dir, ignore_errors=True)  # counted: soak recordings (tens of MB each) must not pile up in /tmp
    t = present_log.snapshot()
    lit = np.isin(t, np.frombuffer(truth_check.lit_t, np.int64))
    result = _analyse(cfg, faults, t, lit, transitions, truth_check.wrong, frames_presented, rows,
                      getattr(loop.parts.recorder, "dropped", 0), rss_start, rss_end, minutes, seed, tracker_status,
                      gaps.snapshot())
    # transitions the monitor had already forgotten when read (would hide causes from the check)
    result["totals"]["safety_transitions_lost"] = (transitions[-1].seq + 1 - len(transitions)) if transitions else 0
    return result


def _frame_ns(t: np.ndarray, lit: np.ndarray, before_ns: int) -> int | None:
    """The loop's frame interval at `before_ns`: the median gap between lit presents in the second before."""
    sel = t[lit & (t < before_ns) & (t >= before_ns - 1_000_000_000)]
    return int(np.median(np.diff(sel))) if len(sel) >= 3 else None


def _tracker_gap(gaps: dict[int, np.ndarray], t_dark: int) -> tuple[int, int] | None:
    """(newest good exposure before the dark frame, first good arrival after it) over the bodies
    whose samples stopped across `t_dark`: the stale rule fires on the oldest body, and tracking is
    good again when the last body's samples are back. None when no body's samples stopped."""
    last_exposure, first_back = [], []
    for g in gaps.values():
        k = np.flatnonzero((g[:, 0] <= t_dark) & (g[:, 2] > t_dark))
        if len(k):
            last_exposure.append(int(g[k[0], 1]))
            first_back.append(int(g[k[0], 2]))
    return (min(last_exposure), max(first_back)) if last_exposure else None


def _ms(ns: int | None) -> float | None:
    return None if ns is None else round(ns / 1e6, 1)


def _analyse(cfg, faults, t, lit, transitions, wrong, frames_presented, rows, rows_dropped, rss_start, rss_end,
             minutes, seed, tracker_status, gaps=None) -> dict:
    gaps = gaps or {}
    stale_ns = int(cfg.safety.stale_after_ms * 1e6)
    holdoff_ns = int(cfg.safety.holdoff_s * 1e9)
    t_end = int(t[-1]) if len(t) else 0
    intervals = _cause_intervals(transitions, t_end)
    lit_in_cause = _lit_inside(t, lit, intervals)
    wrong_t = np.array([w[0] for w in wrong], np.int64)
    rows_out = []
    activations = [(tr.t_ns, tr.name) for tr in transitions if tr.active]
    # one frame where the second before a fault had too few lit frames to tell: the run's median
    lit_t = t[lit]
    run_frame = int(np.median(np.diff(lit_t))) if len(lit_t) >= 3 else None
    clears = np.array(sorted(tr.t_ns for tr in transitions if not tr.active), np.int64)
    attributed = np.zeros(len(t), bool)
    for k, f in enumerate(faults):
        t_next = faults[k + 1].t_inject_ns if k + 1 < len(faults) else t_end + 1
        # a dark spell belongs to this fault only if it began before the fault's end + ATTRIBUTE_S
        # (on a loaded machine the tracker also goes stale on its own; those are counted apart)
        horizon = min(t_next, f.t_clear_ns + int(ATTRIBUTE_S * 1e9))
        dark_idx = np.flatnonzero((t >= f.t_inject_ns) & (t < horizon) & ~lit)
        t_dark = int(t[dark_idx[0]]) if len(dark_idx) else None
        resume_idx = np.flatnonzero((t >= max(f.t_clear_ns, t_dark or 0)) & (t < t_next) & lit)
        t_lit = int(t[resume_idx[0]]) if len(resume_idx) and t_dark is not None else None
        if t_dark is not None:
            attributed |= (t >= t_dark) & (t <= (t_lit or t_next))
        frame = _frame_ns(t, lit, f.t_inject_ns) or run_frame
        # the end of this dark spell (it may end before the fault does, e.g. a stale spell amid noise);
        # one the next fault pre-empted has none here: the next fault's clear is not this one's
        relit_idx = np.flatnonzero((t > (t_dark or 0)) & (t < t_next) & lit)
        t_relit = int(t[relit_idx[0]]) if t_dark is not None and len(relit_idx) else None
        gap = _tracker_gap(gaps, t_dark) if t_dark is not None else None
        t_good = gap[1] if gap is not None and t_relit is not None and gap[1] <= t_relit else None
        # the clear that started the hold-off: the last cause to clear before the spell's first lit frame
        t_cleared = None
        if t_relit is not None:
            c = clears[(clears > t_dark) & (clears <= t_relit)]
            t_cleared = int(c[-1]) if len(c) else None
        window = (t >= f.t_inject_ns) & (t < t_next)
        causes = sorted({name for tn, name in activations if f.t_inject_ns <= tn < horizon})
        row = {
            "kind": f.kind, "detail": f.detail,
            "t_s": round((f.t_inject_ns - faults[0].t_inject_ns) / 1e9, 3),
            "duration_ms": _ms(f.t_clear_ns - f.t_inject_ns),
            "frame_ms": _ms(frame),
            "time_to_dark_ms": None if t_dark is None else _ms(t_dark - f.t_inject_ns),
            "dark_after_last_sample_ms": None if gap is None else _ms(t_dark - gap[0]),
            "time_to_resume_ms": None if t_lit is None else _ms(t_lit - f.t_clear_ns),
            # the device's (or reconnect's) part: for faults that stop the samples only
            "good_sample_after_fault_ms": _ms(t_good - f.t_clear_ns) if t_good is not None and f.kind in TRACKER_KINDS
            else None,
            "cause_clear_after_good_sample_ms": None if t_good is None or t_cleared is None else _ms(t_cleared - t_good),
            "lit_after_good_sample_ms": None if t_good is None else _ms(t_relit - t_good),
            "lit_after_cause_clear_ms": None if t_cleared is None else _ms(t_relit - t_cleared),
            "causes": causes,
            # dark, and the next fault came before a lit frame (the injector waits for one, so ~never)
            "resume_preempted": t_dark is not None and t_relit is None and k + 1 < len(faults),
            "lit_frames_while_cause_active": int((lit_in_cause & window).sum()),
            "implausible_frames_shown": int(((wrong_t >= f.t_inject_ns) & (wrong_t < t_next)).sum()),
            "api_requests": f.api_requests, "api_5xx": f.api_5xx,
        }
        # the goal, per event against that moment's frame interval (tracker faults only)
        if f.kind in TRACKER_KINDS and frame is not None:
            row["dark_within_goal"] = None if gap is None else bool(t_dark - gap[0] <= stale_ns + frame)
            row["resume_within_goal"] = None if t_good is None else bool(t_relit - t_good <= holdoff_ns + frame)
        rows_out.append(row)
    # dark spells no injected fault explains: black presents outside every attributed spell
    first = faults[0].t_inject_ns if faults else t_end
    unexplained = (~lit) & ~attributed & (t >= first)
    starts = np.flatnonzero(unexplained & ~np.concatenate([[False], unexplained[:-1]]))
    unexplained_causes = sorted({name for tn, name in activations if tn >= first} - {
        c for r in rows_out for c in r["causes"]})
    summary = [_summarise(kind, [r for r in rows_out if r["kind"] == kind]) for kind in FAULT_KINDS
               if any(r["kind"] == kind for r in rows_out)]
    fps = cfg.render.target_fps
    return {
        "config": {"minutes": minutes, "seed": seed, "tracker": cfg.tracker.kind,
                   "render_size": [cfg.render.width, cfg.render.height],
                   "stale_after_ms": cfg.safety.stale_after_ms, "holdoff_s": cfg.safety.holdoff_s,
                   "target_fps": fps, "tracker_rate_hz": cfg.mock.rate_hz},
        "faults": rows_out,
        "summary": summary,
        "totals": {
            "faults": len(rows_out), "frames_presented": frames_presented, "lit_presents": int(lit.sum()),
            "recording_rows": rows, "recording_rows_dropped": rows_dropped,
            "lit_frames_while_cause_active": int(lit_in_cause.sum()),
            "implausible_frames_shown": len(wrong),
            "unexplained_dark_spells": len(starts), "unexplained_causes": unexplained_causes,
            "rss_mb_start": round(rss_start, 1), "rss_mb_end": round(rss_end, 1),
            "tracker": {"frames": tracker_status.frames, "malformed": tracker_status.malformed,
                        "implausible": tracker_status.implausible, "out_of_order": tracker_status.out_of_order,
                        "reconnects": tracker_status.reconnects,
                        **{k: tracker_status.details.get(k) for k in (
                            "foreign_datagrams", "frame_resyncs", "clock_outliers", "garbage_bytes")
                           if k in tracker_status.details}},
        },
    }


def _summarise(kind: str, rs: list[dict]) -> dict:
    def stat(key: str, fn) -> float | None:
        v = [r[key] for r in rs if r.get(key) is not None]
        return round(float(fn(v)), 1) if v else None

    def goal(key: str) -> str | None:
        v = [r[key] for r in rs if r.get(key) is not None]
        return f"{sum(v)}/{len(v)}" if v else None

    return {
        "kind": kind, "count": len(rs), "went_dark": sum(r["time_to_dark_ms"] is not None for r in rs),
        "frame_ms_median": stat("frame_ms", np.median),
        "time_to_dark_ms_median": stat("time_to_dark_ms", np.median), "time_to_dark_ms_max": stat("time_to_dark_ms", np.max),
        "dark_after_last_sample_ms_median": stat("dark_after_last_sample_ms", np.median),
        "dark_after_last_sample_ms_max": stat("dark_after_last_sample_ms", np.max),
        "dark_within_goal": goal("dark_within_goal"),
        "time_to_resume_ms_median": stat("time_to_resume_ms", np.median),
        "time_to_resume_ms_max": stat("time_to_resume_ms", np.max),
        "good_sample_after_fault_ms_median": stat("good_sample_after_fault_ms", np.median),
        "lit_after_good_sample_ms_median": stat("lit_after_good_sample_ms", np.median),
        "lit_after_good_sample_ms_max": stat("lit_after_good_sample_ms", np.max),
        "lit_after_cause_clear_ms_median": stat("lit_after_cause_clear_ms", np.median),
        "resume_within_goal": goal("resume_within_goal"),
        "resume_preempted": sum(r["resume_preempted"] for r in rs),
        "lit_frames_while_cause_active": sum(r["lit_frames_while_cause_active"] for r in rs),
        "implausible_frames_shown": sum(r["implausible_frames_shown"] for r in rs),
        "api_5xx": sum(r["api_5xx"] for r in rs),
        "causes": sorted({c for r in rs for c in r["causes"]}),
    }


def format_table(result: dict) -> str:
    c = result["config"]

    def ms(v):
        return "–" if v is None else f"{v:.0f}"

    lines = [f"soak: {c['minutes']:g} min, {c.get('tracker', 'natnet')} tracker, seed {c['seed']}, "
             f"{c['render_size'][0]}×{c['render_size'][1]}, stale_after {c['stale_after_ms']:g} ms, "
             f"hold-off {c['holdoff_s']:g} s",
             "",
             "| fault | n | went dark | frame ms | to dark ms (median / max) | last sample → dark ms (median / max) | "
             "dark within goal | fault end → good sample ms | good sample → lit ms (median / max) | cause clear → lit ms | "
             "resume within goal | lit frames while a cause was active | implausible frames shown | API 5xx | causes raised |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in result["summary"]:
        lines.append(
            f"| {s['kind']} | {s['count']} | {s['went_dark']} | {s['frame_ms_median'] if s['frame_ms_median'] is not None else '–'} | "
            f"{ms(s['time_to_dark_ms_median'])} / {ms(s['time_to_dark_ms_max'])} | "
            f"{ms(s['dark_after_last_sample_ms_median'])} / {ms(s['dark_after_last_sample_ms_max'])} | "
            f"{s['dark_within_goal'] or '–'} | {ms(s['good_sample_after_fault_ms_median'])} | "
            f"{ms(s['lit_after_good_sample_ms_median'])} / {ms(s['lit_after_good_sample_ms_max'])} | "
            f"{ms(s['lit_after_cause_clear_ms_median'])} | {s['resume_within_goal'] or '–'} | "
            f"{s['lit_frames_while_cause_active']} | {s['implausible_frames_shown']} | {s['api_5xx']} | "
            f"{', '.join(s['causes']) or '–'} |")
    t = result["totals"]
    lines += ["", f"frames presented {t['frames_presented']}, recording rows {t['recording_rows']} "
                  f"(dropped {t['recording_rows_dropped']}); lit frames while a cause was active "
                  f"{t['lit_frames_while_cause_active']}; implausible frames shown {t['implausible_frames_shown']}; "
                  f"RSS {t['rss_mb_start']} → {t['rss_mb_end']} MB",
              (f"resumes pre-empted by the next fault (not counted against the goal): "
               f"{sum(s['resume_preempted'] for s in result['summary'])}"),
              f"dark spells no injected fault explains: {t['unexplained_dark_spells']} "
              f"(causes: {', '.join(t['unexplained_causes']) or '–'})",
              f"tracker: {json.dumps(t['tracker'])}",
              "goal: dark within stale_after_ms + one frame of the newest good sample's exposure; lit within "
              "holdoff_s + one frame of the first good sample (one frame: that moment's median frame interval)"]
    return "\n".join(lines)


def plot_soak(result: dict, path: Path) -> None:
    """Per fault kind: every fault's time to dark and time to resume, against the goal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = result["config"]
    kinds = [s["kind"] for s in result["summary"]]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for ax, key, fallback, goal, label in (
            (axes[0], "dark_after_last_sample_ms", "time_to_dark_ms", c["stale_after_ms"],
             f"stale_after_ms ({c['stale_after_ms']:g})"),
            (axes[1], "lit_after_good_sample_ms", "time_to_resume_ms", c["holdoff_s"] * 1e3,
             f"holdoff_s ({c['holdoff_s']:g} s)")):
        for y, kind in enumerate(kinds):
            # tracker faults from the samples' own stamps; the others from the fault's injection / end
            xs = [r[key] if r.get(key) is not None else r[fallback] for r in result["faults"]
                  if r["kind"] == kind and (r.get(key) is not None or r[fallback] is not None)]
            ax.scatter(xs, np.full(len(xs), y) + np.linspace(-0.2, 0.2, len(xs)), s=10, alpha=0.6)
        ax.axvline(goal, color="k", ls="--", lw=1, label=label)
        ax.set_xscale("symlog", linthresh=10)
        ax.set_xlim(left=0)
        ax.set_xlabel(f"{key.replace('_', ' ')} (per fault; else {fallback.replace('_', ' ')})")
        ax.legend(loc="lower right", fontsize=8)
    axes[0].set_yticks(range(len(kinds)), kinds)
    axes[0].set_ylabel("fault kind")
    fig.suptitle(f"dpmhw bench soak: {c.get('tracker', 'natnet')}, {c['minutes']:g} min, {result['totals']['faults']} "
                 f"faults, seed {c['seed']} "
                 f"(faults that never went dark have no point)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
