"""Every session setting at its bounds and past them, through `dpmhw session config` and, for a
cheap subset, a real `dpmhw session start --mock`: accepted (costly values with a warning that
names the field) or refused in one line that names it; never a traceback, an exit 70 or a start
that does not end."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import annotated_types as at
import pytest
from pydantic import BaseModel
from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.session.config import BAUDRATES, MAX_BODY_ID, MAX_SET_DEPTH, MAX_STATIONS, MAX_TEXT, SessionConfig

SMALL = ["render.width=64", "render.height=48"]  # a start's output: 16×12 shading pixels at ¼
START_TIMEOUT_S = 300  # a start with --duration 1 ends in seconds; this only catches one that never ends
# (generous: the first start on a loaded 2-core machine waits for the compiled-kernel cache)


def _fields() -> dict[str, tuple[type, list]]:
    """'section.field' → (annotation, bound metadata) for every section field."""
    out = {}
    for section, info in SessionConfig.model_fields.items():
        model = info.annotation
        if isinstance(model, type) and issubclass(model, BaseModel):
            out.update({f"{section}.{name}": (f.annotation, f.metadata) for name, f in model.model_fields.items()})
    return out


def _bounds(metadata: list) -> tuple[float, float, bool]:
    lo = hi = None
    strict = False
    for m in metadata:
        if isinstance(m, at.Ge):
            lo = m.ge
        elif isinstance(m, at.Gt):
            lo, strict = m.gt, True
        elif isinstance(m, at.Le):
            hi = m.le
    return lo, hi, strict


def _toml(value) -> str:
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value == math.inf else "-inf" if value == -math.inf else repr(value))
    return str(value)


# a field whose bound is not ge/le metadata, with its own cases below (or, for the pair, both set)
SPECIAL = {"render.width", "render.height", "render.shading_scale", "tracker.baudrate", "tracker.workspace_min",
           "tracker.workspace_max"}


def numeric_cases() -> list[tuple[list[str], str | None]]:
    """(overrides, the field a refusal names or None: accepted) from every numeric field's bounds."""
    cases = []
    for path, (ann, metadata) in _fields().items():
        if ann not in (int, float) or path in SPECIAL:
            continue
        lo, hi, strict = _bounds(metadata)
        assert lo is not None and hi is not None, f"{path}: a number without both bounds"
        if ann is int:
            cases += [([f"{path}={lo}"], None), ([f"{path}={hi}"], None), ([f"{path}={lo - 1}"], path),
                      ([f"{path}={hi + 1}"], path), ([f"{path}={2**64}"], path), ([f"{path}={-(2**100)}"], path),
                      ([f"{path}=1.5"], path), ([f'{path}="x"'], path), ([f"{path}=[1]"], path)]
        else:
            first = math.nextafter(lo, math.inf) if strict else lo
            first = max(first, sys.float_info.min) if first > 0 else first  # the smallest accepted: a normal float
            cases += [([f"{path}={_toml(first)}"], None), ([f"{path}={_toml(float(hi))}"], None),
                      ([f"{path}={_toml(float(lo) if strict else math.nextafter(lo, -math.inf))}"], path),
                      ([f"{path}={_toml(math.nextafter(hi, math.inf))}"], path)]
            cases += [([f"{path}={v}"], path) for v in ("nan", "inf", "-inf", "1e309", "5e-324", '"x"', "{a=1}")]
    return cases


def special_cases() -> list[tuple[list[str], str | None]]:
    bunny = "object='bunny'"
    return [
        (["render.width=16", "render.height=12"], None),
        (["render.width=16384", "render.height=16384"], "render.width, render.height"),  # the memory limit
        (["render.width=3840", "render.height=2160"], None),  # 4K at ¼ fits the default limit
        (["render.width=5120", "render.height=2880", "render.shading_scale=1"], "render.width, render.height"),
        (["render.width=64"], "render"), (["render.width=16385", "render.height=1"], "render.width"),
        (["render.shading_scale=0.3"], "render.shading_scale"), (["render.shading_scale=nan"], "render.shading_scale"),
        (["render.shading_scale=1"], None),
        *[([f"tracker.baudrate={b}"], None) for b in (BAUDRATES[0], 115200, BAUDRATES[-1])],
        *[([f"tracker.baudrate={b}"], "tracker.baudrate") for b in (0, -1, 115201, 99999999999999, 2**64)],
        (["tracker.workspace_min=[nan,nan,nan]"], "tracker.workspace_min"),
        (["tracker.workspace_max=[inf,1,1]"], "tracker.workspace_max"),
        (["tracker.workspace_max=[1e5,1,1]"], "tracker.workspace_max"),
        (["tracker.workspace_min=[1,2]"], "tracker.workspace_min"),
        (["tracker.workspace_min=[-1e4,-1e4,-1e4]", "tracker.workspace_max=[1e4,1e4,1e4]"], None),
        (["tracker.workspace_min=[5,0,0]", "tracker.workspace_max=[5,1,1]"], "tracker"),
        ([f"bindings=[{{rigid_body={MAX_BODY_ID},{bunny}}}]"], None),
        ([f"bindings=[{{rigid_body={MAX_BODY_ID + 1},{bunny}}}]"], "bindings[0].rigid_body"),
        ([f"bindings=[{{rigid_body=-1,{bunny}}}]"], "bindings[0].rigid_body"),
        (["bindings=[{rigid_body=1,object=''}]"], "bindings[0].object"),
        (["tracker.kind=serial", f"bindings=[{{rigid_body={MAX_STATIONS},{bunny}}}]"], None),
        (["tracker.kind=serial", f"bindings=[{{rigid_body={MAX_STATIONS + 1},{bunny}}}]"], "bindings[0].rigid_body"),
        (["tracker.kind=serial", f"bindings=[{{rigid_body=0,{bunny}}}]"], "bindings[0].rigid_body"),
        (['scene.source="a\\u0000b"'], "scene.source"), ([f'sink.path="{"x" * (MAX_TEXT + 1)}"'], "sink.path"),
        ([f'recording.path="{"x" * MAX_TEXT}"'], None), (['tracker.server="host\\nname"'], "tracker.server"),
        (['api.token="a b"'], "api.token"), (['api.token="abc-_.~+/=="'], None), (['api.token="tök"'], "api.token"),
        (["scene.source=no-such-scene.toml"], "scene"), (["scene.calibration=nope.json"], "scene.calibration"),
        (["sink.kind=file"], "sink.path"), (["sink.kind=file", "sink.path=out"], None),
        (["render.filter=magic"], "render.filter"), (["lod.moving_every=3"], "lod.moving_every"),
        (["render.analytic=maybe"], "render.analytic"), (["mock.trajectory=[1]"], "mock.trajectory"),
        (["render.spp=" + "[" * 5000 + "]" * 5000], "--set render.spp"),
        ([f"render.spp={'[' * MAX_SET_DEPTH}1{']' * MAX_SET_DEPTH}"], "render.spp"),  # at the bound: parsed, then refused
        (['scene.source="[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["'], "scene"),  # brackets in a string do not nest
    ]


def _config(overrides: list[str]):
    _register()
    return CliRunner().invoke(app, ["session", "config", "--offline", *(a for o in overrides for a in ("--set", o))])


def _check(output: str, code: int, refused: str | None, where: str) -> None:
    assert "Traceback" not in output and code != 70, where
    errors = [line for line in output.splitlines() if line.startswith("error:")]
    if refused is None:
        assert code == 0 and not errors, where
    else:
        assert code == 2 and len(errors) == 1, where
        assert refused in errors[0] and len(errors[0]) <= 600, where  # a long value is shown cut


@pytest.mark.parametrize("overrides, refused", numeric_cases() + special_cases(),
                         ids=lambda v: " ".join(v)[:60] if isinstance(v, list) else str(v))
def test_session_config_accepts_the_bounds_and_refuses_past_them_in_one_line(overrides, refused):
    result = _config(overrides)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    _check(result.output, result.exit_code, refused, result.output[-2000:])


def test_the_table_covers_every_field():
    """A field added without bounds, or missing from the table, fails here."""
    covered = {o.partition("=")[0] for overrides, _ in numeric_cases() + special_cases() for o in overrides}
    numeric = {p for p, (ann, _) in _fields().items() if ann in (int, float) or p in SPECIAL}
    assert numeric <= covered, numeric - covered
    text = {p for p, (ann, _) in _fields().items() if ann is str}
    assert len(text) >= 10  # every text field shares one rule (tested on a few above)


@pytest.mark.parametrize("overrides, named", [
    (["render.target_fps=0.5"], "render.target_fps=0.5"),
    ([f"render.threads={max(os.cpu_count() or 1, 1) + 1}"], "render.threads="),
    (["metrics.window=1000000"], "metrics.window=1000000"),
    (["lod.rays=1073741824", "lod.moving=true"], "lod.rays=1073741824"),
    (["render.adaptive_rays=16777216"], "render.adaptive_rays=16777216"),
])
def test_costly_values_are_accepted_with_a_warning_saying_what_they_cost(overrides, named):
    result = _config(overrides)
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.output.splitlines() if line.startswith("warning:")]
    assert len(warnings) >= 1 and named in warnings[0], result.output


def test_the_defaults_warn_of_nothing_and_report_the_memory_estimate():
    result = _config([])
    assert result.exit_code == 0
    assert "warning:" not in result.output
    assert "memory: about" in result.output and "1024×768 output" in result.output  # dpm-bunny's projector


def _start(overrides: list[str], duration: float = 1.0) -> tuple[int, str]:
    args = ["session", "start", "--mock", "--no-api", "--duration", str(duration), "--status-every", "0"]
    args += [a for o in [*SMALL, *overrides] for a in ("--set", o)]
    proc = subprocess.run([sys.executable, "-c", "from dpmhw.cli import main; main()", *args], capture_output=True,
                          text=True, timeout=START_TIMEOUT_S, env={**os.environ, "DPMHW_API_TOKEN": "t"})
    return proc.returncode, proc.stdout + proc.stderr


START_CASES = [
    # the hostile values, each now refused before the loop process starts (exit 2, no allocation)
    (["render.width=8192", "render.height=8192"], "render.width, render.height"),
    ([f"bindings=[{{rigid_body={2**31},object='bunny'}}]"], "bindings[0].rigid_body"),
    (["tracker.baudrate=99999999999999"], "tracker.baudrate"),
    # what `session config` accepts, at the bounds, starts and stops
    ([f"bindings=[{{rigid_body={MAX_BODY_ID},object='bunny'}}]", "render.threads=256", "metrics.window=1000000",
      "render.target_fps=0.001", f"render.seed={2**32 - 1}", "render.spp=64", "lod.rays=1073741824",
      "lod.moving=true", "render.adaptive_rays=16777216", "mock.rate_hz=10000"], None),
    (["tracker.kind=serial", f"tracker.baudrate={BAUDRATES[-1]}", "bindings=[{rigid_body=1,object='bunny'}]"], None),
]


@pytest.mark.parametrize("overrides, refused", START_CASES, ids=lambda v: " ".join(v)[:60] if isinstance(v, list) else str(v))
def test_what_session_config_accepts_starts_with_the_mocks(overrides, refused):
    code, output = _start(overrides)
    _check(output, code, refused, output[-3000:])
    if refused is not None:
        assert "loop process" not in output  # refused before the loop process (or anything at that size) started
    else:  # the start names what `session config` names
        said = [line for line in _config([*SMALL, *overrides]).output.splitlines() if line.startswith(("warning:", "memory:"))]
        assert said and all(line in output.splitlines() for line in said), output[-3000:]


def sweep_cases() -> list[list[str]]:
    """Every numeric field at each accepted bound, one start each (the serial mock numbers its
    stations 1…n, so a start binds station 1: START_CASES)."""
    return [overrides for overrides, refused in numeric_cases() + special_cases()
            if refused is None and not any(o.startswith(("render.width", "render.height", "tracker.kind")) for o in overrides)
            and not any('"' in o for o in overrides)]


@pytest.mark.slow
@pytest.mark.parametrize("overrides", sweep_cases(), ids=lambda v: " ".join(v)[:60])
def test_every_accepted_bound_starts_with_the_mocks(overrides):
    code, output = _start(overrides)
    _check(output, code, None, output[-3000:])


@pytest.mark.slow
@pytest.mark.parametrize("overrides, refused", [
    (["sink.kind=file", "sink.path=/proc/no-such-folder/out.mp4"], "sink.path"),
    (["recording.enabled=true", "recording.path=/proc/no-such-folder"], "recording.path"),
    (['scene.mesh="/no-such-mesh.obj"'], "objects[0].mesh"),
    (['tracker.server="no.such.host.invalid"'], None),  # dark: the tracker says it is lost
], ids=lambda v: " ".join(v)[:60] if isinstance(v, list) else str(v))
def test_paths_and_hosts_that_only_a_start_can_check_fail_in_one_line(overrides, refused):
    code, output = _start(overrides)
    _check(output, code, refused, output[-3000:])


def test_a_scene_whose_own_size_needs_too_much_is_refused_by_session_config_and_by_a_start(tmp_path, monkeypatch):
    """Output size 0×0 is the scene's: the estimate reads it from the scene file (no mesh loaded),
    and opening the parts checks the loaded scene again. A small scene under a small limit: were
    the check gone, the start would allocate only that much."""
    from scene_texts import lit_room

    from dpmhw.limits import SESSION_BASE_BYTES, SESSION_BYTES_PER_PIXEL
    from dpmhw.session.config import SessionConfigError, load_session_config
    from dpmhw.session.factory import open_session_parts

    scene = tmp_path / "room.toml"
    scene.write_text(lit_room("", width=640, height=480, f=500.0, cx=319.5, cy=239.5, max_bounces=0))
    need_mib = {s: (SESSION_BASE_BYTES + 640 * 480 * b) / 2**20 for s, b in SESSION_BYTES_PER_PIXEL.items()}
    monkeypatch.setenv("DPMHW_SESSION_MEMORY_MB", str(int((need_mib[0.25] + need_mib[1.0]) / 2)))  # ¼ fits, 1 not
    bound = [f"scene.source={scene}", 'bindings=[{rigid_body=1,object="room"}]']  # a session needs a tracked object
    overrides = [*bound, "render.shading_scale=1"]
    result = _config(overrides)
    _check(result.output, result.exit_code, "render.width, render.height (0: scene.source's size)", result.output)
    assert _config(bound).exit_code == 0
    with pytest.raises(SessionConfigError, match="over the limit"):
        open_session_parts(load_session_config(overrides=overrides), mock=True)


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1.0, 0.25])
def test_the_memory_estimate_covers_a_started_sessions_peak(scale):
    """The peak RSS of a mock start (its loop process included) stays below the estimate."""
    from dpmhw.limits import session_memory

    width, height = 1280, 960
    args = ["session", "start", "--mock", "--no-api", "--duration", "3", "--status-every", "0",
            "--set", f"render.width={width}", "--set", f"render.height={height}", "--set", f"render.shading_scale={scale}"]
    probe = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, check=True); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")  # KiB, the largest descendant
    out = subprocess.run([sys.executable, "-c", probe, sys.executable, "-c", "from dpmhw.cli import main; main()", *args],
                         capture_output=True, text=True, timeout=START_TIMEOUT_S, check=True)
    peak = int(out.stdout.split()[-1]) * 1024
    need, _ = session_memory(width, height, scale)
    assert peak <= need, (peak / 2**20, need / 2**20)
    assert peak > need / 2  # the estimate is of this session, not a bound anything meets
