"""Reading back the ``sweep.h5`` table a sweep writes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

__all__ = ["read_table", "read_table_layout"]


def read_table(path: Path) -> list[dict[str, Any]]:
    """Rows of a ``sweep.h5`` table (parameter columns keep their dotted names; missing numbers are None)."""
    with h5py.File(path, "r") as handle:
        columns = json.loads(handle.attrs["columns"])
        data = {}
        for c in columns:
            dataset = handle["table"][c]
            missing = dataset.attrs.get("missing_value")
            values = dataset[()]
            data[c] = [_cell(v, missing) for v in values]
    n = len(next(iter(data.values()))) if data else 0
    return [{c: data[c][i] for c in columns} for i in range(n)]


def read_table_layout(path: Path) -> tuple[str, list[str]]:
    """The study of a ``sweep.h5`` table and its parameter columns (dotted config keys), in column order."""
    with h5py.File(path, "r") as handle:
        columns = json.loads(handle.attrs["columns"])
        study = handle.attrs.get("study", "")
        study = study.decode() if isinstance(study, bytes) else str(study)
        parameters = [c for c in columns if bool(handle["table"][c].attrs.get("parameter", False))]
    return study, parameters


def _cell(value, missing):
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.integer):
        return None if missing is not None and int(value) == int(missing) else int(value)
    if isinstance(value, np.floating):
        return None if np.isnan(value) else float(value)
    return value
