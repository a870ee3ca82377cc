"""The command line: every command has --help; errors are one clear line, not a traceback."""
import subprocess
import sys

import pytest
import typer
from typer.testing import CliRunner

from splatzoo.cli import app

runner = CliRunner()
COMMANDS = sorted(c.name or c.callback.__name__ for c in app.registered_commands)


def test_commands_exist():
    assert "models" in COMMANDS


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command):
    result = runner.invoke(app, [command, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output and len(result.output) > 100


def test_models_lists_builtins():
    result = runner.invoke(app, ["models"])
    assert result.exit_code == 0
    for name in ("2dgs", "gabor", "baseline-a", "baseline-b", "baseline-c"):
        assert name in result.output
    assert "built-in" in result.output


def test_console_script_reports_errors_without_traceback(tmp_path):
    out = subprocess.run([sys.executable, "-m", "splatzoo.cli", "nonexistent-command"], capture_output=True, text=True)
    assert out.returncode != 0 and "Traceback" not in out.stderr
