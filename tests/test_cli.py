from typer.testing import CliRunner

from dpmhw import __version__
from dpmhw.cli import _register, app


def test_version_and_help():
    _register()
    runner = CliRunner()
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert __version__ in result.output
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    assert "bench" in result.output


# ---- help and messages name the real option and cause (issue 16) ---------------------------------

import json  # noqa: E402
import re  # noqa: E402

import pytest  # noqa: E402


def _run(*args, **kw):
    _register()
    return CliRunner().invoke(app, [*map(str, args)], **kw)


def test_help_shows_bracketed_defaults_and_no_bool_metavar():
    out = _run("render", "--help").output
    assert "[default: 16; 1 per frame with --frames]" in " ".join(out.split())
    assert "<bool>" not in out and "--warmup " in out
    assert "<off|same-pixel|motion>" in out and "<clip|reinhard>" in out
    out = " ".join(_run("bench", "quality", "--help").output.split())
    assert "[default: $DPMHW_CACHE/references or ~/.cache/dpmhw/references]" in out


@pytest.mark.parametrize("args, option", [
    (["render", "x.toml", "--reuse", "moton"], "--reuse"),
    (["render", "x.toml", "--tonemap", "aces"], "--tonemap"),
    (["bench", "quality", "--part", "both"], "--part"),
    (["bench", "session", "--trajectory", "zigzag"], "--trajectory"),
    (["bench", "session", "--api-mode", "fork"], "--api-mode"),
    (["bench", "reproject", "--trajectory", "zigzag"], "--trajectory"),
    (["bench", "stages", "--trajectory", "zigzag"], "--trajectory"),
    (["bench", "governor", "--trajectory", "zigzag"], "--trajectory"),
    (["bench", "governor", "--hog-processes", "0"], "--hog-processes"),
    (["mock", "natnet", "--version", "5.0"], "--version"),
    (["mock", "natnet", "--data-port", "0"], "--data-port"),
    (["mock", "serial", "--model", "XX"], "--model"),
])
def test_bad_choices_fail_at_parse_time_naming_the_option(args, option):
    result = _run(*args)
    assert result.exit_code == 2
    assert f"Invalid value for '{option}'" in result.output


def test_bench_governor_refuses_a_hog_after_the_end():
    result = _run("bench", "governor", "--seconds", "5", "--hog-after", "5")
    assert result.exit_code == 2 and "--hog-after 5 must be less than --seconds 5" in result.output


def test_render_alpha_error_names_the_option(tmp_path):
    result = _run("render", "x.toml", "--frames", "2", "--alpha", "0")
    assert result.exit_code == 2 and "Invalid value for --alpha: expected a number in (0, 1]" in result.output


def test_set_errors_name_the_command_line():
    result = _run("session", "config", "--set", "render.spp=0")
    assert result.exit_code == 2
    assert "command line: render.spp" in result.output and "(defaults)" not in result.output


def test_projector_list_names_a_missing_libusb(monkeypatch):
    import usb.core

    def no_backend(*a, **kw):
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", no_backend)
    result = _run("projector", "list")
    assert result.exit_code == 1
    assert "no USB backend" in result.output and "libusb" in result.output and "no DLPC900" not in result.output


TINY_SCENE = """
[render]
width = 16
height = 12
[camera]
fx = 15.0
fy = 15.0
cx = 8.0
cy = 6.0
position = [0.0, 0.0, 2.0]
look_at = [0.0, 0.0, 0.0]
[[objects]]
name = "lamp"
shape = "sphere"
radius = 0.5
emission = [1.0, 1.0, 1.0]
"""


def test_render_frames_into_out_dir_writes_nothing_else(tmp_path, monkeypatch):
    (tmp_path / "s.toml").write_text(TINY_SCENE)
    monkeypatch.chdir(tmp_path)
    result = _run("render", "s.toml", "--frames", "2", "--out-dir", "seq")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "seq").iterdir()) == ["frame_00000.png", "frame_00001.png", "frames.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml", "seq"]
    assert json.loads((tmp_path / "seq" / "frames.json").read_text())["frames"] == 2


def test_render_sidecar_is_file_dot_suffix_dot_json(tmp_path):
    (tmp_path / "s.toml").write_text(TINY_SCENE)
    result = _run("render", tmp_path / "s.toml", "--spp", "2", "--out", tmp_path / "f.npy")
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "f.npy.json").read_text())["spp"] == 2
    assert re.search(r"rendering 16×12, passes: 2/2 \(100 %\), done in", result.output)  # progress in a log


@pytest.mark.parametrize("args, option", [(["--size", "10x"], "--size"), (["--starts", "a"], "--starts"),
                                          (["--horizons", "5,-1"], "horizons")])
def test_bench_reproject_refuses_bad_values_naming_them(args, option):
    result = _run("bench", "reproject", *args)
    assert result.exit_code == 2 and option in result.output


def test_bench_reproject_writes_flat_rows_with_the_machine(tmp_path):
    path = tmp_path / "rp.json"
    result = _run("bench", "reproject", "--size", "96x72", "--spp", "2", "--starts", "0.3", "--horizons", "20",
                  "--repeats", "2", "--threads", "1", "--json", path)
    assert result.exit_code == 0, result.output
    rows = json.loads(path.read_text())
    assert len(rows) == 1 and rows[0]["horizon_ms"] == 20 and rows[0]["lit"] > 0 and "machine_cpu_model" in rows[0]
    assert rows[0]["ms_per_present_pattern"] > 0 and rows[0]["psnr_db"] > 0 and "ms/reproj" in result.output
