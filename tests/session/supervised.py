"""`dpmhw session start` with a fault injected into the loop process, for test_supervisor.py:

    python -m tests.session.supervised abort session start --mock …

runs the real CLI, whose supervisor passes the named hook below to each loop process it starts
(`Supervisor(on_loop_started=…)`). Each hook arms once the loop has presented a frame, prints
the CLOCK_MONOTONIC instant of the fault (one clock for every process: the test measures time to
dark from it) and then crashes the loop process its way.
"""

from __future__ import annotations

import functools
import os
import sys
import threading
import time


def _after_first_frame(kind: str, crash) -> None:
    def arm(loop) -> None:
        while loop.status().get("frame_number", 0) < 1:
            time.sleep(0.01)
        sys.stderr.write(f"injected {kind} at monotonic_ns {time.monotonic_ns()}\n")
        sys.stderr.flush()
        crash(loop)

    return arm


def _abort(loop) -> None:
    os.abort()  # SIGABRT, as a native crash ends a process


def _raise_in_loop_thread(loop) -> None:
    publish = loop._publish

    def failing(force: bool = False) -> None:
        loop._publish = publish
        raise RuntimeError("injected: an exception escaping the loop thread")

    loop._publish = failing  # called outside the loop's per-iteration try: it escapes the thread


def abort(loop) -> None:
    threading.Thread(target=_after_first_frame("abort", _abort), args=(loop,), daemon=True).start()


def loop_exception(loop) -> None:
    threading.Thread(target=_after_first_frame("loop-exception", _raise_in_loop_thread), args=(loop,),
                     daemon=True).start()


def main() -> None:
    from dpmhw.cli import main as cli
    from dpmhw.session import supervisor
    from tests.session import supervised  # by its importable name: the loop process unpickles the hook by it

    hook = getattr(supervised, sys.argv[1].replace("-", "_"))
    supervisor.Supervisor = functools.partial(supervisor.Supervisor, on_loop_started=hook)
    sys.argv = [sys.argv[0], *sys.argv[2:]]
    cli()


if __name__ == "__main__":
    main()
