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
