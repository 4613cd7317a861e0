"""`--ray [ADDRESS]` on the command line: a bare `--ray` means a local Ray instance, an address is
passed on, and the other options parse as they did. Ray itself is replaced by a recorder here
(test_ray.py runs the real thing)."""

import json

import pytest
from typer.testing import CliRunner

from dpmhw.cli import _register, app
from dpmhw.cli.optional_value import fill_bare_options
from dpmhw.errors import DpmhwError


@pytest.fixture
def connect_calls(monkeypatch):
    """The addresses the CLI asks Ray for; the render then goes on locally (None = no pool)."""
    import dpmhw.cluster.ray_pool as ray_pool

    calls = []

    def recorder(address):
        calls.append(address)
        return None

    monkeypatch.setattr(ray_pool, "connect", recorder)
    _register()
    return calls


@pytest.mark.parametrize("ray_args, address", [
    (["--ray"], "local"),                          # last on the line
    (["--ray", "--seed", "3"], "local"),           # followed by another option
    (["--ray", "local"], "local"),
    (["--ray", "HEAD:6379"], "HEAD:6379"),
    (["--ray=ray://HEAD:10001"], "ray://HEAD:10001"),
    ([], None),                                    # no --ray: no Ray
])
def test_render_ray_without_an_address_means_local(connect_calls, scene_file, tmp_path, ray_args, address):
    out = tmp_path / "f.npy"
    result = CliRunner().invoke(app, ["render", str(scene_file), "--spp", "2", *ray_args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert connect_calls == [address]
    meta = json.loads((tmp_path / "f.npy.json").read_text())
    assert meta["ray"] == address and meta["spp"] == 2  # --spp and --out still parsed
    assert meta["seed"] == (3 if "--seed" in ray_args else 0)


def test_a_bare_ray_before_the_scene_takes_the_scene_as_its_address(connect_calls, scene_file, tmp_path):
    """As with any optional value: the next word that is not an option is the value."""
    result = CliRunner().invoke(app, ["render", "--ray", str(scene_file), "--out", str(tmp_path / "f.npy")])
    assert connect_calls == [str(scene_file)], result.output


@pytest.mark.parametrize("ray_args, address", [(["--ray"], "local"), (["--ray", "--threads", "1"], "local"),
                                               (["--ray", "HEAD:6379"], "HEAD:6379")])
def test_bench_quality_ray_without_an_address_means_local(monkeypatch, tmp_path, ray_args, address):
    import dpmhw.cluster.ray_pool as ray_pool

    calls = []

    def refuse(addr):  # stop before the benchmark runs
        calls.append(addr)
        raise DpmhwError("no cluster in this test")

    monkeypatch.setattr(ray_pool, "connect", refuse)
    _register()
    result = CliRunner().invoke(app, ["bench", "quality", *ray_args, "--cache-dir", str(tmp_path)])
    assert result.exit_code == 2 and "no cluster in this test" in result.output
    assert calls == [address]


def test_fill_bare_options_steps_over_other_options_values():
    defaults, counts = {"--ray": "local"}, {"--out": 1, "-o": 1, "--pair": 2}
    assert fill_bare_options(["s", "--ray"], defaults, counts) == ["s", "--ray=local"]
    assert fill_bare_options(["--ray", "-o", "x"], defaults, counts) == ["--ray=local", "-o", "x"]
    assert fill_bare_options(["--ray", "-"], defaults, counts) == ["--ray", "-"]  # "-" is a value
    assert fill_bare_options(["--out", "--ray"], defaults, counts) == ["--out", "--ray"]  # a file named --ray
    assert fill_bare_options(["--pair", "a", "--ray", "--ray"], defaults, counts) == ["--pair", "a", "--ray", "--ray=local"]
    assert fill_bare_options(["--", "--ray"], defaults, counts) == ["--", "--ray"]
    assert fill_bare_options(["--ray", "h:1", "--ray"], defaults, counts) == ["--ray", "h:1", "--ray=local"]
