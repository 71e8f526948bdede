"""Saving figures: PNG bytes rendered in memory, then written atomically."""
from __future__ import annotations

import io
from pathlib import Path

from estcal.base.atomic import atomic_write_bytes

__all__ = ["save_figure"]


def save_figure(fig, path, dpi: int = 90) -> Path:
    """Render ``fig`` (a :class:`matplotlib.figure.Figure`) to PNG and write it to ``path``
    atomically (a killed run leaves the old file or the new one, never half a PNG)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return atomic_write_bytes(path, buf.getvalue())
