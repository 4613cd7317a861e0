"""Suite-wide settings: property tests are judged on what the code returns, never on how fast a
loaded machine ran one example (hypothesis's 200-ms deadline and its too-slow health check are
wall-clock checks; a CPU hog beside the suite tripped neither only by luck)."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("dpmhw", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("dpmhw")


def pytest_sessionstart(session) -> None:
    """Compile the session's kernels once, up front and in parallel, with progress in the log:
    otherwise the first test to render pays for it inside its own time limit, and a fixture that
    starts a session waits minutes on a fresh clone. Nothing to do when the cache is warm."""
    from dpmhw.session.config import load_session_config
    from dpmhw.session.warmup import compile_kernels

    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    write = (lambda line: reporter.write_line(line)) if reporter is not None else print
    result = compile_kernels(load_session_config(None), progress=lambda p: None if p.warm else write(p.line()),
                             every_s=15.0)
    for group, why in result.failed.items():
        write(f"compiling the {group} kernels ahead failed ({why}); the tests compile them as they go")


def pytest_xdist_auto_num_workers(config) -> int:
    """`-n auto` (pyproject's addopts): a worker per core, 2 to 4. Much of the suite waits on
    sessions, sockets and subprocesses against the wall clock, so two workers nearly halve its
    time even on 2 cores; each test is sized for a loaded 2-core machine, and more workers than
    cores would load it beyond that. `-n 0` runs it in this process."""
    return min(4, max(2, os.cpu_count() or 1))


@pytest.fixture(autouse=True, scope="session")
def _own_runtime_dir(tmp_path_factory):
    """Session lock files (dpmhw.session.instance) in a directory of this run's own, so a suite
    run beside another one's mock sessions sees no 'another --mock session' warning."""
    os.environ["DPMHW_RUNTIME_DIR"] = str(tmp_path_factory.mktemp("runtime"))
