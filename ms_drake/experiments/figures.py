"""Writing the experiments' figures as PNG files (matplotlib's Agg backend: no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt


def figure_dir(out_dir) -> Path:
    """`out_dir`, made if missing, after switching matplotlib to the Agg backend."""
    matplotlib.use("Agg")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir


def save_png(fig, path: Path, dpi: int = 120) -> Path:
    """Lay `fig` out tightly, write it to `path` at `dpi` and close it; returns `path`."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
