"""Session recording: tracker poses, per-frame timings and a subsample of frames, for review.

One folder per session (`<parent>/session-YYYYmmdd-HHMMSS/`):

    config.json    the resolved session config (token masked)
    frames.csv     one row per presented frame: times, the quality governor's level (0: the
                   configured settings), stage durations, every live setting
                   (`LiveSettings`, flags as 0/1), pose used per body
    poses.csv      every tracker sample (body, exposure time, valid, position, quaternion xyzw)
    frames/NNNNNN.png   every `frame_every`-th presented frame

The loop only puts rows on a bounded queue (a full queue drops and counts, never blocks); a
writer thread appends them and flushes + fsyncs at least once a second, so a crash loses at
most the last second.
"""

from __future__ import annotations

import csv
import json
import os
import queue
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dpmhw.session.config import LiveSettings

__all__ = ["SessionRecorder"]

FLUSH_EVERY_S = 1.0
_STAGES = ("tracker_age", "predict", "render", "reuse", "post", "present", "frame")


class SessionRecorder:
    def __init__(self, folder: Path, frame_every: int = 30, tracker=None, queue_size: int = 4096):
        self.folder = Path(folder)
        (self.folder / "frames").mkdir(parents=True, exist_ok=False)
        self.frame_every = frame_every
        self.dropped = 0
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._stop = threading.Event()
        self._frames_file = open(self.folder / "frames.csv", "w", newline="")
        self._poses_file = open(self.folder / "poses.csv", "w", newline="")
        self._frames = csv.writer(self._frames_file)
        self._poses = csv.writer(self._poses_file)
        self._frames.writerow(["number", "t_start_ns", "t_target_ns", "t_present_ns", "sample_age_ms",
                               "governor_level", *[f"{s}_ms" for s in _STAGES], *LiveSettings.model_fields, "body", "sample_t_exposure_ns", "x", "y", "z", "qx", "qy", "qz", "qw"])
        self._poses.writerow(["body", "t_exposure_ns", "t_arrival_ns", "frame_number", "valid", "x", "y", "z",
                              "qx", "qy", "qz", "qw"])
        self._subscription = tracker.subscribe(maxlen=8192) if hasattr(tracker, "subscribe") else None
        self._thread = threading.Thread(target=self._run, name="session-recorder", daemon=True)
        self._thread.start()

    @classmethod
    def create(cls, parent: Path, config, tracker=None) -> "SessionRecorder":
        folder = Path(parent) / datetime.now().strftime("session-%Y%m%d-%H%M%S-%f")
        rec = cls(folder, config.recording.frame_every, tracker)
        data = config.model_dump()
        data["api"]["token"] = "***" if data["api"]["token"] else ""
        (folder / "config.json").write_text(json.dumps(data, indent=2))
        return rec

    # ---- called by the loop ------------------------------------------------------------------
    def frame(self, record, image: np.ndarray) -> None:
        """Queue one presented frame (the image only every `frame_every` frames). Never blocks."""
        keep = image if record.number % self.frame_every == 0 else None
        try:
            self._queue.put_nowait((record, keep))
        except queue.Full:
            self.dropped += 1

    # ---- writer thread -------------------------------------------------------------------------
    def _write_frame(self, record, image) -> None:
        settings = [int(v) if isinstance(v, bool) else v for v in record.settings.model_dump().values()]
        stages = [round(record.stages_s.get(k, float("nan")) * 1e3, 4) for k in _STAGES]
        for body, pose in record.poses.items():
            q = Rotation.from_matrix(pose.R).as_quat()
            self._frames.writerow([record.number, record.t_start_ns, record.t_target_ns, record.t_present_ns,
                                   round(record.sample_age_s * 1e3, 4), record.governor_level,
                                   *stages, *settings, body,
                                   record.sample_t_ns.get(body), *np.round(pose.t, 6),
                                   *np.round(q, 8)])
        if image is not None:
            from dpmhw.postprocess import write_png

            write_png(self.folder / "frames" / f"{record.number:06d}.png", image)

    def _write_samples(self) -> None:
        if self._subscription is None:
            return
        for s in self._subscription.drain():
            q = Rotation.from_matrix(s.rotation).as_quat() if s.valid and np.all(np.isfinite(s.rotation)) else [np.nan] * 4
            self._poses.writerow([s.rigid_body_id, s.t_exposure_ns, s.t_arrival_ns, s.frame_number, int(s.valid),
                                  *np.round(s.translation, 6), *np.round(q, 8)])

    def _flush(self) -> None:
        for f in (self._frames_file, self._poses_file):
            f.flush()
            os.fsync(f.fileno())

    def _run(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=0.1)
            except queue.Empty:
                item = None
            if item is not None:
                self._write_frame(*item)
            if time.monotonic() - last_flush >= FLUSH_EVERY_S or (item is None and self._stop.is_set()):
                self._write_samples()
                self._flush()
                last_flush = time.monotonic()
            if item is None and self._stop.is_set() and self._queue.empty():
                return

    def close(self) -> None:
        """Write what is queued, flush, close the files."""
        self._stop.set()
        self._thread.join(timeout=30)
        if self._subscription is not None:
            self._subscription.close()
        self._write_samples()
        self._flush()
        self._frames_file.close()
        self._poses_file.close()
