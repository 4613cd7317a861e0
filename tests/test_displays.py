"""`dpmhw displays`: the listing and the match against the projector's native size, from an
injected list and, where Xvfb is installed, from a real X server."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from drivers.displays import Display, DisplayList
from dpmhw.cli import _register, app
from dpmhw.cli.displays import describe_displays

ROOT = Path(__file__).resolve().parents[1]
MONITOR = Display(0, "DELL U2720Q", (3840, 2160), (60, 30))
PROJECTOR = Display(1, "DLP6500", (1920, 1080), (60,))


def test_the_display_at_the_native_size_is_named_and_a_wrong_sink_display_is_corrected():
    found = DisplayList("x11", (MONITOR, PROJECTOR))
    lines = describe_displays(found, (1920, 1080), configured=0)
    assert lines[0] == "display 0: 'DELL U2720Q' 3840×2160 @ 60 Hz (also 30 Hz)  <- sink.display"
    assert lines[1] == "display 1: 'DLP6500' 1920×1080 @ 60 Hz  <- projector's native size"
    assert lines[2] == ("sink.display = 0 is not at the projector's native 1920×1080; display 1 is: "
                        "set sink.display = 1")
    assert describe_displays(found, (1920, 1080), configured=1)[-1] == \
        "sink.display = 1 runs at the projector's native 1920×1080"


def test_no_display_at_the_native_size_or_at_the_configured_index_is_said():
    found = DisplayList("x11", (MONITOR,))
    lines = describe_displays(found, (1024, 768), configured=2)
    assert lines[-2] == "sink.display = 2: no such display (1 attached)"
    assert lines[-1].startswith("no display runs at the projector's native 1024×768")


def test_headless_says_no_display_in_one_line():
    """No display server: SDL's offscreen driver invents a screen; it is not listed as one."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", "from dpmhw.cli import main; main()", "displays"],
                         capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("\n") == 1 and out.stdout.startswith("no display: "), out.stdout


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="needs Xvfb (apt install xvfb)")
def test_an_xvfb_screen_is_listed_and_matched(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", sys.executable, "-c",
                          "from dpmhw.cli import main; main()", "displays", "--set", "sink.display=0"],
                         capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].startswith("display 0: ") and " 1024×768" in lines[0] and "projector's native size" in lines[0]
    assert lines[-1] == "sink.display = 0 runs at the projector's native 1024×768"  # the built-in scene's size


def test_a_bad_config_is_one_line_and_exit_2():
    _register()
    result = CliRunner().invoke(app, ["displays", "--set", "render.width=-1"])
    assert result.exit_code == 2 and "render.width" in result.output
