"""Soak test: a mock session (emulated Motive over NatNet, emulated DLPC900 over pyusb, the real
drivers and loop) with faults injected one at a time at random moments, for `minutes`.

Fault kinds (`FAULT_KINDS`), each injected only while the session is projecting:

    tracker_stall        the NatNet server sends nothing for 0.3–1.5 s
    tracker_restart      the server stops; 0.2–1 s later a new one (frame numbers and clock begin
                         again) answers on the same port
    corrupt_datagrams    for 1–3 s, 30 % of the frames are truncated or have bytes flipped
    foreign_datagrams    for 1–3 s, another address (127.0.0.2) sends frames at 360 Hz with a pose
                         1 km away and frame numbers 10⁶ ahead
    implausible_sample   one or two genuine frames carry a pose 2 m away (inside the workspace:
                         caught by the speed limit) or 1 km away (outside it)
    implausible_burst    genuine frames carry a pose 50 m away (outside the workspace) for 0.2–1 s
                         (a sustained offset *inside* the workspace is, by design, accepted once
                         it is reachable at `max_speed_m_s`: kinematics cannot tell it from a move)
    usb_stall            the projector's next 3 USB transfers fail (halted endpoint)
    usb_unplug           the projector is unplugged for 0.5–2 s, then replugged (power-cycled)
    api_load             for 3 s, two clients hammer the API process with hostile requests (NaN,
                         wrong types, oversized bodies, bad tokens) and status reads

Per fault, from the presented frames (a wrapper around the sink logs every present with
whether it was lit) and the safety monitor's transitions:

- time to dark: injection → the first black frame (None when the show stayed lit);
- time to resume: end of the fault → the next lit frame;
- lit frames presented while a safety cause was active (must be 0), and lit frames whose pose was
  more than 0.5 m from the truth (the implausible ones; must be 0);
- the API answers with status ≥ 500 (must be 0).

At the end: recording rows (frames.csv) against frames presented, and the process RSS at start
and end. The goal (issue 14): tracker faults dark within `stale_after_ms` + one frame and back
within `holdoff_s` + one frame of the fault's end (a restart also needs the reconnect).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import random
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
from dpmhw.tracking import wait_for

__all__ = ["FAULT_KINDS", "format_table", "plot_soak", "run_soak"]

log = logging.getLogger(__name__)

FAULT_KINDS = ("tracker_stall", "tracker_restart", "corrupt_datagrams", "foreign_datagrams", "implausible_sample",
               "implausible_burst", "usb_stall", "usb_unplug", "api_load")
TRACKER_KINDS = ("tracker_stall", "tracker_restart", "implausible_burst")
_WRONG_POSE_M = 0.5  # a lit frame whose pose is this far from the truth showed an implausible pose
ATTRIBUTE_S = 1.0  # a dark spell starting later than this after a fault's end is not that fault's


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


class _PresentLog:
    """Wraps the session's sink: logs (time, lit) of every present, compactly. `is_lit()` is read
    at each present: the loop lowers its output flag before it presents a black frame."""

    def __init__(self, sink, is_lit: Callable[[], bool]):
        self.sink = sink
        self.is_lit = is_lit
        self.t = array("q")
        self.lit = array("b")
        self._lock = threading.Lock()

    def present(self, frame, t_target_ns: int) -> int:
        t = self.sink.present(frame, t_target_ns)
        with self._lock:
            self.t.append(t)
            self.lit.append(1 if self.is_lit() else 0)
        return t

    def __getattr__(self, name):
        return getattr(self.sink, name)

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            return np.frombuffer(self.t, np.int64).copy(), np.frombuffer(self.lit, np.int8).astype(bool)


class _TruthCheck:
    """Wraps the recorder: every presented frame's measured pose is compared with the world's true
    pose at the sample's instant (the trajectories as built, before any glitch)."""

    def __init__(self, recorder, truths: dict[int, Callable], epoch_s: float):
        self.recorder = recorder
        self.truths = truths
        self.epoch_s = epoch_s
        self.wrong: list[tuple[int, float]] = []  # (t_present_ns, metres off)

    def frame(self, record, image) -> None:
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


class _Glitch:
    """A trajectory that adds `offset` (metres) to another one's translation while set."""

    def __init__(self, inner):
        self.inner = inner
        self.offset = np.zeros(3)

    def pose(self, t):
        rot, pos = self.inner.pose(t)
        return rot, pos + self.offset


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
        self.glitches: dict[int, _Glitch] = {}
        self.first_server = self.rig.natnet
        world = self.rig.world
        for body, obj in list(world.objects.items()):
            glitch = _Glitch(obj.trajectory)
            world.objects[body] = dataclasses.replace(obj, trajectory=glitch)
            self.glitches[body] = glitch
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
        old = self.server
        port = old.command_port
        old.stop()
        time.sleep(down)
        cfg = dataclasses.replace(old.config, command_port=port, server_uptime_s=self.rng.uniform(10.0, 1e5),
                                  seed=self.rng.randrange(2**31))
        for _ in range(50):  # the old socket may take a moment to release the port
            try:
                new = type(old)(self.rig.world, cfg).start()
                break
            except OSError:
                time.sleep(0.02)
        else:
            raise RuntimeError(f"soak: cannot restart the NatNet mock on port {port}")
        self.rig.natnet = new
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
        bodies = list(self.glitches)
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
        for g in self.glitches.values():
            g.offset = np.asarray(offset, float)
        try:
            wait_for(until, 5.0, poll_s=0.0005)
        finally:
            for g in self.glitches.values():
                g.offset = np.zeros(3)

    def implausible_sample(self, fault: _Fault) -> None:
        sent = self.server.frames_sent
        metres = self.rng.choice([2.0, 1000.0])
        # the mock encodes each frame one period ahead: two frames sent means one glitched
        self._glitch((metres, 0.0, 0.0), lambda: self.server.frames_sent > sent + 1)
        fault.detail = f"{self.server.frames_sent - sent} frame(s) {metres:g} m off"
        fault.t_clear_ns = time.monotonic_ns()

    def implausible_burst(self, fault: _Fault) -> None:
        seconds = self.rng.uniform(0.2, 1.0)
        end = time.monotonic() + seconds
        self._glitch((50.0, 0.0, 0.0), lambda: time.monotonic() >= end)
        fault.detail = f"{seconds:.2f} s 50 m off"
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
        if self.rig.natnet is not self.first_server:  # a restarted server: the rig only stops the first
            self.rig.natnet.stop()


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


def run_soak(minutes: float, *, seed: int = 0, kinds: tuple[str, ...] = FAULT_KINDS, gap_s: tuple[float, float] = (1.5, 4.0),
             width: int = 128, height: int = 96, overrides: tuple[str, ...] = (),
             progress: Callable[[str], None] | None = None) -> dict:
    """Run the soak; returns {"config": …, "faults": [per fault], "summary": [per kind], "totals": …}."""
    from dpmhw.session.factory import build_session

    unknown = sorted(set(kinds) - set(FAULT_KINDS))
    if unknown:
        raise ValueError(f"unknown fault kinds {unknown}; known: {', '.join(FAULT_KINDS)}")
    rng = random.Random(seed)
    token = "soak-token"
    rec_dir = Path(tempfile.mkdtemp(prefix="dpmhw-soak-"))
    cfg = load_session_config(overrides=[
        f"render.width={width}", f"render.height={height}", "sink.kind=recording", "api.enabled=false",
        "recording.enabled=true", f"recording.path={rec_dir}", f"api.token={token}", *overrides])
    loop = build_session(cfg, mock=True)
    world = loop.parts.mock.world
    truths = {body: obj.trajectory.pose for body, obj in world.objects.items()}
    present_log = _PresentLog(loop.parts.sink, lambda: loop._output_on)
    loop.parts.sink = present_log
    truth_check = _TruthCheck(loop.parts.recorder, truths, world.epoch_s)
    loop.parts.recorder = truth_check
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
        while time.monotonic() < t_end:
            time.sleep(rng.uniform(*gap_s))
            # inject only into a projecting session, so each fault's dark and resume are its own
            if not wait_for(lambda: loop.status()["state"] == "running", 30):
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
        tracker_details = loop.parts.tracker.status()
    finally:
        injector.close()
        loop.stop()
    frames_presented = loop.status()["frame_number"]  # final: published by stop()
    # the recorder flushed and closed with the loop: count its rows now
    rows = sum(max(0, sum(1 for _ in open(p)) - 1) for p in rec_dir.glob("*/frames.csv"))
    t, lit = present_log.snapshot()
    result = _analyse(cfg, faults, t, lit, transitions, truth_check.wrong, frames_presented, rows,
                      getattr(loop.parts.recorder, "dropped", 0), rss_start, rss_end, minutes, seed, tracker_details)
    # transitions the monitor had already forgotten when read (would hide causes from the check)
    result["totals"]["safety_transitions_lost"] = (transitions[-1].seq + 1 - len(transitions)) if transitions else 0
    return result


def _analyse(cfg, faults, t, lit, transitions, wrong, frames_presented, rows, rows_dropped, rss_start, rss_end,
             minutes, seed, tracker_status) -> dict:
    t_end = int(t[-1]) if len(t) else 0
    intervals = _cause_intervals(transitions, t_end)
    lit_in_cause = _lit_inside(t, lit, intervals)
    wrong_t = np.array([w[0] for w in wrong], np.int64)
    rows_out = []
    activations = [(tr.t_ns, tr.name) for tr in transitions if tr.active]
    attributed = np.zeros(len(t), bool)
    for k, f in enumerate(faults):
        t_next = faults[k + 1].t_inject_ns if k + 1 < len(faults) else t_end + 1
        # a dark spell belongs to this fault only if it began before the fault's end + ATTRIBUTE_S
        # (on a loaded machine the tracker also goes stale on its own; those are counted apart)
        horizon = min(t_next, f.t_clear_ns + int(ATTRIBUTE_S * 1e9))
        dark_idx = np.flatnonzero((t >= f.t_inject_ns) & (t < horizon) & ~lit)
        t_dark = int(t[dark_idx[0]]) if len(dark_idx) else None
        resume_idx = np.flatnonzero((t >= max(f.t_clear_ns, t_dark or 0)) & (t < t_next) & lit)
        t_resume = int(t[resume_idx[0]]) if len(resume_idx) and t_dark is not None else None
        if t_dark is not None:
            attributed |= (t >= t_dark) & (t <= (t_resume or t_next))
        window = (t >= f.t_inject_ns) & (t < t_next)
        causes = sorted({name for tn, name in activations if f.t_inject_ns <= tn < horizon})
        rows_out.append({
            "kind": f.kind, "detail": f.detail,
            "t_s": round((f.t_inject_ns - faults[0].t_inject_ns) / 1e9, 3),
            "duration_ms": round((f.t_clear_ns - f.t_inject_ns) / 1e6, 1),
            "time_to_dark_ms": None if t_dark is None else round((t_dark - f.t_inject_ns) / 1e6, 1),
            "time_to_resume_ms": None if t_resume is None else round((t_resume - f.t_clear_ns) / 1e6, 1),
            "causes": causes,
            "lit_frames_while_cause_active": int((lit_in_cause & window).sum()),
            "implausible_frames_shown": int(((wrong_t >= f.t_inject_ns) & (wrong_t < t_next)).sum()),
            "api_requests": f.api_requests, "api_5xx": f.api_5xx,
        })
    # dark spells no injected fault explains: black presents outside every attributed spell
    first = faults[0].t_inject_ns if faults else t_end
    unexplained = (~lit) & ~attributed & (t >= first)
    starts = np.flatnonzero(unexplained & ~np.concatenate([[False], unexplained[:-1]]))
    unexplained_causes = sorted({name for tn, name in activations if tn >= first} - {
        c for r in rows_out for c in r["causes"]})
    summary = []
    for kind in FAULT_KINDS:
        rs = [r for r in rows_out if r["kind"] == kind]
        if not rs:
            continue
        dark = [r["time_to_dark_ms"] for r in rs if r["time_to_dark_ms"] is not None]
        resume = [r["time_to_resume_ms"] for r in rs if r["time_to_resume_ms"] is not None]
        summary.append({
            "kind": kind, "count": len(rs), "went_dark": len(dark),
            "time_to_dark_ms_median": float(np.median(dark)) if dark else None,
            "time_to_dark_ms_max": float(np.max(dark)) if dark else None,
            "time_to_resume_ms_median": float(np.median(resume)) if resume else None,
            "time_to_resume_ms_max": float(np.max(resume)) if resume else None,
            "lit_frames_while_cause_active": sum(r["lit_frames_while_cause_active"] for r in rs),
            "implausible_frames_shown": sum(r["implausible_frames_shown"] for r in rs),
            "api_5xx": sum(r["api_5xx"] for r in rs),
            "causes": sorted({c for r in rs for c in r["causes"]}),
        })
    fps = cfg.render.target_fps
    return {
        "config": {"minutes": minutes, "seed": seed, "render_size": [cfg.render.width, cfg.render.height],
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
                        "foreign_datagrams": tracker_status.details.get("foreign_datagrams"),
                        "frame_resyncs": tracker_status.details.get("frame_resyncs"),
                        "clock_outliers": tracker_status.details.get("clock_outliers")},
        },
    }


def format_table(result: dict) -> str:
    c = result["config"]

    def ms(v):
        return "–" if v is None else f"{v:.0f}"

    lines = [f"soak: {c['minutes']:g} min, seed {c['seed']}, {c['render_size'][0]}×{c['render_size'][1]}, "
             f"stale_after {c['stale_after_ms']:g} ms, hold-off {c['holdoff_s']:g} s",
             "",
             "| fault | n | went dark | to dark ms (median / max) | to resume ms (median / max) | lit frames while a cause was active | implausible frames shown | API 5xx | causes raised |",
             "|---|---|---|---|---|---|---|---|---|"]
    for s in result["summary"]:
        lines.append(f"| {s['kind']} | {s['count']} | {s['went_dark']} | {ms(s['time_to_dark_ms_median'])} / "
                     f"{ms(s['time_to_dark_ms_max'])} | {ms(s['time_to_resume_ms_median'])} / {ms(s['time_to_resume_ms_max'])} | "
                     f"{s['lit_frames_while_cause_active']} | {s['implausible_frames_shown']} | {s['api_5xx']} | "
                     f"{', '.join(s['causes']) or '–'} |")
    t = result["totals"]
    lines += ["", f"frames presented {t['frames_presented']}, recording rows {t['recording_rows']} "
                  f"(dropped {t['recording_rows_dropped']}); lit frames while a cause was active "
                  f"{t['lit_frames_while_cause_active']}; implausible frames shown {t['implausible_frames_shown']}; "
                  f"RSS {t['rss_mb_start']} → {t['rss_mb_end']} MB",
              f"dark spells no injected fault explains: {t['unexplained_dark_spells']} "
              f"(causes: {', '.join(t['unexplained_causes']) or '–'})",
              f"tracker: {json.dumps(t['tracker'])}"]
    return "\n".join(lines)


def plot_soak(result: dict, path: Path) -> None:
    """Per fault kind: every fault's time to dark and time to resume, against the goal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = result["config"]
    kinds = [s["kind"] for s in result["summary"]]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for ax, key, goal, label in (
            (axes[0], "time_to_dark_ms", c["stale_after_ms"], f"stale_after_ms ({c['stale_after_ms']:g})"),
            (axes[1], "time_to_resume_ms", c["holdoff_s"] * 1e3, f"holdoff_s ({c['holdoff_s']:g} s)")):
        for y, kind in enumerate(kinds):
            xs = [r[key] for r in result["faults"] if r["kind"] == kind and r[key] is not None]
            ax.scatter(xs, np.full(len(xs), y) + np.linspace(-0.2, 0.2, len(xs)), s=10, alpha=0.6)
        ax.axvline(goal, color="k", ls="--", lw=1, label=label)
        ax.set_xscale("symlog", linthresh=10)
        ax.set_xlim(left=0)
        ax.set_xlabel(f"{key.replace('_', ' ')} (per fault)")
        ax.legend(loc="lower right", fontsize=8)
    axes[0].set_yticks(range(len(kinds)), kinds)
    axes[0].set_ylabel("fault kind")
    fig.suptitle(f"dpmhw bench soak: {c['minutes']:g} min, {result['totals']['faults']} faults, seed {c['seed']} "
                 f"(faults that never went dark have no point)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
