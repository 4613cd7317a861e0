"""Readying the kernels: worker groups report progress, failures and stops; the groups cover the
session's own warm-up; once a session is built, no frame compiles anything."""

from __future__ import annotations

import sys
import time

import numba
import pytest

from dpmhw.session import warmup
from dpmhw.session.config import load_session_config
from dpmhw.session.warmup import TRUST_PACE_AT, CompileProgress, KernelGroup, compile_kernels, eta_s


def _add(a, b):
    return a + b


def _mul(a, b):
    return a * b


def _tiny_kernels(config_data: dict) -> None:
    """Compiles `_add` for two signatures and `_mul` for one (no cache), as a group would."""
    add, mul = numba.njit(_add), numba.njit(_mul)
    assert add(1, 2) == 3 and add(1.0, 2.0) == 3.0 and mul(2.0, 3.0) == 6.0


def _broken(config_data: dict) -> None:
    raise ValueError("scene.source: no such file")


def _forever(config_data: dict) -> None:
    while True:
        time.sleep(1)


def test_groups_in_workers_report_kernels_progress_and_failures():
    seen: list[CompileProgress] = []
    groups = {"tiny": KernelGroup(_tiny_kernels, {"test_warmup._add": 1.0}),
              "broken": KernelGroup(_broken, {"x.never": 1.0})}
    result = compile_kernels({}, groups=groups, force=True, workers=2,
                             progress=lambda p: seen.append(CompileProgress(**vars(p))))
    assert result.groups_left == [] and not result.stopped and not result.warm
    assert result.failed == {"broken": "ValueError: scene.source: no such file"}
    assert result.done == 1 and result.expected == 2  # a listed kernel counts once, whatever its signatures
    add = result.kernels["test_warmup._add"]
    assert add["group"] == "tiny" and add["signatures"] == 2 and add["seconds"] > 0
    assert result.kernels["test_warmup._mul"]["signatures"] == 1  # compiled, timed, not counted: not listed
    assert seen and seen[-1].groups_left == []
    assert "1/2 kernels" in result.line() and result.line().endswith("done")


def test_the_eta_follows_the_pace_of_a_slower_cpu():
    """The table says 36 s; this CPU compiles 3× slower (108 s). Before anything is done the
    table is all there is; from TRUST_PACE_AT of the work on, the ETA is the observed pace's."""
    assert eta_s(0.0, 0.0, 36.0) == 36.0
    assert eta_s(TRUST_PACE_AT * 108, TRUST_PACE_AT, 36.0) == pytest.approx(108 * (1 - TRUST_PACE_AT))
    assert eta_s(54.0, 0.5, 36.0) == pytest.approx(54.0)
    half_way_in = TRUST_PACE_AT / 2  # blended: between the table's 36 s and the truth, 108 s
    assert 36.0 - 108 * half_way_in < eta_s(108 * half_way_in, half_way_in, 36.0) < 108 * (1 - half_way_in)
    assert eta_s(10.0, 0.999, 36.0) >= 0.0


def test_a_stop_ends_the_workers_at_once():
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 3

    t0 = time.monotonic()
    result = compile_kernels({}, groups={"hang": KernelGroup(_forever, {})}, force=True, should_stop=stop)
    assert result.stopped and result.groups_left == ["hang"]
    assert time.monotonic() - t0 < 60  # bound for a loaded machine: the spawn; the stop itself is a kill


def test_a_warm_cache_starts_no_worker(monkeypatch):
    monkeypatch.setattr(warmup, "cache_is_warm", lambda: True)
    monkeypatch.setattr(warmup.multiprocessing, "get_context", lambda *a: pytest.fail("a worker was started"))
    lines = []
    result = compile_kernels({}, progress=lambda p: lines.append(p.line()))
    assert result.warm and lines == ["render kernels: loaded from the cache"]


def _overloads() -> dict[str, int]:
    """Compiled signatures of every numba dispatcher in dpmhw's modules (in this process)."""
    out = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith("dpmhw.") or module is None:
            continue
        for attr, value in vars(module).items():
            for i, d in enumerate(value if isinstance(value, tuple) else (value,)):
                if isinstance(d, numba.core.registry.CPUDispatcher):
                    out[f"{name}.{attr}[{i}]"] = len(d.overloads)
    return out


def _new(before: dict[str, int], after: dict[str, int]) -> dict[str, int]:
    return {k: n - before.get(k, 0) for k, n in after.items() if n > before.get(k, 0)}


@pytest.mark.parametrize("extra", [[], ["lod.mesh=true"]], ids=["default", "mesh-lod"])
def test_the_groups_cover_the_session_and_no_frame_compiles(extra):
    """The worker groups (run here, in this process) leave the session's own warm-up nothing to
    compile, and frames in every reuse mode and filter compile nothing after it."""
    from dpmhw.session.factory import build_session
    from dpmhw.session.testing import wait_for

    cfg = load_session_config(None, ["render.width=96", "render.height=72", *extra])
    data = cfg.model_dump()
    for group in warmup.GROUPS.values():
        group.run(data)
    before = _overloads()
    loop = build_session(cfg, mock=True)
    try:
        built = _overloads()
        # the serial G-buffer attributes are for regions too small for threads, which synthetic frames do not make
        assert {k for k in _new(before, built) if "_attributes_py" not in k and not (extra and ".lod." in k)} == set()
        loop.start()
        for mode in ("off", "same-pixel", "motion"):
            for filt in ("off", "normal", "lobe"):
                loop.update_settings({"reuse_mode": mode, "filter": filt})
                applied = lambda: loop.status()["settings_applied"]  # noqa: E731
                assert wait_for(lambda: (applied()["reuse_mode"], applied()["filter"]) == (mode, filt), 120), loop.status()
                n = loop.status()["frame_number"]
                assert wait_for(lambda: loop.status()["frame_number"] >= n + 3, 120), loop.status()
        assert _new(built, _overloads()) == {}
    finally:
        loop.stop()
