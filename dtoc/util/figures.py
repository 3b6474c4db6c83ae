"""Matplotlib figures rendered to deterministic PNG bytes (no software/date metadata)."""

from __future__ import annotations

import io


def png_bytes(fig, dpi: int = 90) -> bytes:
    """Lay out ``fig``, render it as PNG and close it; the same figure gives the same bytes."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()
