"""Strict JSON for every report dtoc writes (command --json output, the optimize manifest).

Indented, key-sorted, numpy scalars as Python numbers, NaN/inf as null: every consumer can parse it, and the
same content gives the same bytes.
"""

from __future__ import annotations

import json
import math
from typing import Any


def strict_json(obj: Any) -> str:
    """Indented, key-sorted JSON; NaN/inf become null so that every consumer can parse it."""

    def clean(x):
        if hasattr(x, "item") and getattr(x, "ndim", 1) == 0:  # numpy scalars
            x = x.item()
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    return json.dumps(clean(obj), indent=2, sort_keys=True, allow_nan=False) + "\n"
