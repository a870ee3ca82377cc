"""What the reports (splatzoo compare, splatzoo sweep) share: matplotlib without a display, figures written
atomically, and metrics read back from their JSON."""
from __future__ import annotations

from pathlib import Path

from .io import atomic_path


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> None:
    """Write `fig` as a PNG at `path`, atomically."""
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")


def metric(v) -> float:
    """A metric from JSON as a float: null (a non-finite value, e.g. the PSNR of a perfect render) is NaN."""
    return float("nan") if v is None else float(v)
