"""The `splatzoo` command line: a thin shell over functions a user can call from Python.

Heavy imports (open3d, pycolmap, cv2, the native extension) stay inside the commands.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .errors import SplatzooError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="splatzoo: surface splatting model zoo (2DGS, 3D Gabor splatting and plugins).")


@app.command("models")
def models_command() -> None:
    """List the available models: name, origin (built-in or plugin) and description; broken plugins say why."""
    from .registry import MODELS

    for entry in MODELS.entries():
        if entry.broken:
            typer.echo(f"{entry.name:<14} {entry.origin:<24} BROKEN: {entry.error}")
        else:
            typer.echo(f"{entry.name:<14} {entry.origin:<24} {entry.spec.description}")


@app.callback()
def _root() -> None:
    """splatzoo: surface splatting model zoo (2DGS, 3D Gabor splatting and plugins)."""


# --- data commands (splatzoo sfm, splatzoo synth) ---------------------------------------------------------
# (data commands go here)

# --- rasterizer benchmark (splatzoo bench) ----------------------------------------------------------------
# (bench command goes here)

# --- training and evaluation (train, eval, render, compare) ---------------------------------------------
# (training commands go here)


def main() -> None:
    """Entry point: splatzoo's own errors become one clear line and exit code 2 (no traceback)."""
    try:
        app()
    except SplatzooError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
