"""One session per projector: the lock file under the runtime directory."""

from __future__ import annotations

import os

import pytest
from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.session.config import SessionConfigError, load_session_config
from dpmhw.session.instance import SessionLock


@pytest.fixture(autouse=True)
def runtime(monkeypatch, tmp_path):
    monkeypatch.setenv("DPMHW_RUNTIME_DIR", str(tmp_path))
    return tmp_path


def test_a_second_session_on_the_projector_is_refused_with_the_first_ones_pid():
    cfg = load_session_config(overrides=['projector.serial="A1"'])
    first = SessionLock.claim(cfg, mock=False)
    with pytest.raises(SessionConfigError, match=rf"^projector: another session \(pid {os.getpid()}\) drives DLPC900 A1 "):
        SessionLock.claim(cfg, mock=False)
    other = SessionLock.claim(load_session_config(overrides=['projector.serial="B2"']), mock=False)  # another projector
    first.release()
    SessionLock.claim(cfg, mock=False).release()
    other.release()


def test_a_second_mock_session_is_warned_and_a_projectorless_one_locks_nothing():
    cfg = load_session_config()
    first = SessionLock.claim(cfg, mock=True)
    second = SessionLock.claim(cfg, mock=True)
    assert not first.warning and f"another --mock session runs on this machine (pid {os.getpid()}" in second.warning
    none = load_session_config(overrides=['projector.kind="none"'])
    assert SessionLock.claim(none, mock=False).path is None and SessionLock.claim(none, mock=False).path is None
    first.release()


def test_a_lock_file_left_by_a_dead_session_is_taken_over(runtime):
    (runtime / "dlpc900-first-attached.lock").write_text("999999\n")
    lock = SessionLock.claim(load_session_config(), mock=False)
    assert (runtime / "dlpc900-first-attached.lock").read_text() == f"{os.getpid()}\n"
    lock.release()


def test_session_start_refuses_a_taken_projector_before_anything_loads():
    _register()
    lock = SessionLock.claim(load_session_config(), mock=False)
    try:
        r = CliRunner().invoke(app, ["session", "start", "--no-api", "--duration", "1"])
    finally:
        lock.release()
    assert r.exit_code == 2 and r.output == f"error: projector: another session (pid {os.getpid()}) drives the projector " \
                                             f"({lock.path})\n", r.output
