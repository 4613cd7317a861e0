"""One session per projector: a lock file under the runtime directory, holding the owner's pid.

A hardware session locks its projector (`dlpc900-<serial>.lock`; a second one is refused with
the first one's pid); a `--mock` session locks `mock.lock`, and a second one on the same machine
runs with a warning (the two share the CPU, so each runs slower). The lock is an `flock` on the
open file, which the kernel drops when its process ends, so a file a dead session left behind
is simply taken over.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

from dpmhw.session.config import SessionConfig, SessionConfigError


def runtime_dir() -> Path:
    """$DPMHW_RUNTIME_DIR, else $XDG_RUNTIME_DIR/dpmhw, else <tmp>/dpmhw-<uid>."""
    if os.environ.get("DPMHW_RUNTIME_DIR"):
        return Path(os.environ["DPMHW_RUNTIME_DIR"])
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "dpmhw"
    return Path(tempfile.gettempdir()) / f"dpmhw-{os.getuid()}"


class SessionLock:
    """Held from `claim` until `release` (or the process ends)."""

    def __init__(self, path: Path | None, fd: int | None, warning: str = ""):
        self.path, self._fd, self.warning = path, fd, warning

    @classmethod
    def claim(cls, config: SessionConfig, mock: bool) -> "SessionLock":
        """Lock what this session drives. Raises SessionConfigError naming the other session's
        pid when a hardware session's projector is taken; on the mocks returns an unheld lock
        whose `warning` says so instead. A hardware session without a projector locks nothing."""
        if not mock and config.projector.kind == "none":
            return cls(None, None)
        serial = config.projector.serial or "first-attached"
        name = "mock.lock" if mock else f"dlpc900-{serial}.lock"
        directory = runtime_dir()
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        path = directory / name
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            other = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            if mock:
                return cls(path, None, f"warning: another --mock session runs on this machine (pid {other}, {path}); "
                                       "the two share the CPU, so both run slower")
            what = f"DLPC900 {config.projector.serial}" if config.projector.serial else "the projector"
            raise SessionConfigError(f"projector: another session (pid {other}) drives {what} ({path})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return cls(path, fd)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays for the next session to take
            self._fd = None
