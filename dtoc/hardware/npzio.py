"""Deterministic ``.npz`` writing (same arrays -> byte-identical file) through the atomic writer.

``numpy.savez`` stamps the current time into the zip entries, so two runs differ; here entries are
written in sorted key order with a fixed timestamp and no compression.
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np

from dtoc.util.atomic import atomic_write_bytes


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """The bytes of an uncompressed ``.npz`` holding ``arrays`` (no pickles), deterministic."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for key in sorted(arrays):
            arr = np.asarray(arrays[key])
            if arr.dtype == object:
                raise TypeError(f"npz key {key!r}: object arrays are not written")
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            data = io.BytesIO()
            np.lib.format.write_array(data, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(info, data.getvalue())
    return buf.getvalue()


def save_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray], force: bool = False) -> Path:
    """Atomically write a deterministic ``.npz``."""
    return atomic_write_bytes(path, npz_bytes(arrays), force=force)
