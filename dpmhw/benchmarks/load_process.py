"""A load generator in a process of its own (spawned, never forked from a process running native
threads), so that its clients never share the CPU time or the interpreter lock of the process
they load: the session bench's API clients, the API storm, flood and probes (`server.storm`).

    class Clients(LoadProcess):
        def __init__(self, port):
            super().__init__("api-clients", _clients, (port,))   # _clients(port, active, stop, ready, out)
        def _collect(self):
            self.results = self._out.get(timeout=30)

    with Clients(port) as load:
        load.active.set()          # they work while this is set
        ...
    load.results                   # what they put on `out` once stopped
"""

from __future__ import annotations

import multiprocessing
import threading
from typing import Callable

__all__ = ["LoadProcess", "run_threads"]


class LoadProcess:
    """A spawned process running `target(*args, active, stop, ready, out)`: it sets `ready` once
    it runs, works while `active` is set and puts what it found on `out` when `stop` is set,
    which `_collect` takes back."""

    def __init__(self, name: str, target: Callable, args: tuple):
        ctx = multiprocessing.get_context("spawn")
        self.ready, self.active, self._stop = ctx.Event(), ctx.Event(), ctx.Event()
        self._out = ctx.Queue()
        self.process = ctx.Process(target=target, name=name, daemon=True,
                                   args=(*args, self.active, self._stop, self.ready, self._out))

    def __enter__(self):
        self.process.start()
        if not self.ready.wait(60):
            self.close()
            raise RuntimeError(f"the {self.process.name} process did not start")
        return self

    def close(self) -> None:
        self.active.clear()
        self._stop.set()
        if self.process.pid is not None:
            self._collect()
        self.process.join(5)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5)

    def __exit__(self, *exc) -> None:
        self.close()

    def _collect(self) -> None:
        raise NotImplementedError


def run_threads(count: int, target: Callable[[int], None], ready) -> None:
    """In the load process: `target(i)` on `count` threads, `ready` set once they run, until
    every one has returned."""
    threads = [threading.Thread(target=target, args=(i,), daemon=True) for i in range(count)]
    for t in threads:
        t.start()
    ready.set()
    for t in threads:
        t.join()
