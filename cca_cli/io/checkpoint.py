"""Reconstruction checkpoints, and the spectrum of an earlier recon.h5 to start from.

A checkpoint ``<output>.checkpoint`` is a cca HDF5 file written beside the
output (temporary file + rename, so a kill leaves the previous one whole). It
holds the engine's state under /checkpoint (arrays as datasets, scalars as
attributes), the history so far under /history, and the fingerprint of the
inputs and options it belongs to (attribute ``fingerprint`` of /checkpoint).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from cca_cli.io.h5 import Provenance, atomic_h5, write_dataset
from cca_cli.io.outputs import is_cca_hdf5

__all__ = ["Checkpoint", "checkpoint_path", "write_checkpoint", "read_checkpoint", "checkpoint_damage",
           "remove_checkpoint"]

_HISTORY = ("residual", "change", "seconds")


@dataclass(frozen=True)
class Checkpoint:
    """What a checkpoint file holds."""

    fingerprint: str
    state: dict
    history: dict[str, np.ndarray]


def checkpoint_path(output: str | Path) -> Path:
    """``<output>.checkpoint`` beside ``output``."""
    output = Path(output)
    return output.with_name(output.name + ".checkpoint")


def write_checkpoint(path: Path, provenance: Provenance, fingerprint: str, state: dict,
                     history: dict[str, np.ndarray]) -> None:
    """Replace the checkpoint at ``path`` atomically (only a file cca wrote is ever replaced)."""
    with atomic_h5(path, provenance, force=True) as handle:
        group = handle.create_group("checkpoint")
        group.attrs["fingerprint"] = fingerprint
        for name, value in state.items():
            if isinstance(value, np.ndarray):
                write_dataset(handle, f"/checkpoint/{name}", value)
            else:
                group.attrs[name] = value
        for name in history:
            write_dataset(handle, f"/history/{name}", np.asarray(history[name], np.float64))


def read_checkpoint(path: Path) -> Checkpoint | None:
    """The checkpoint at ``path``; None when there is none, or it is not a readable checkpoint cca wrote."""
    if not path.is_file() or not is_cca_hdf5(path):
        return None
    try:
        with h5py.File(path, "r") as handle:
            group = handle["checkpoint"]
            state = {name: np.asarray(group[name]) for name in group}
            state.update({name: value for name, value in group.attrs.items() if name != "fingerprint"})
            fingerprint = group.attrs["fingerprint"]
            history = {name: np.asarray(handle[f"/history/{name}"], np.float64) for name in handle["history"]}
            if not set(_HISTORY) <= set(history):
                return None
    except (OSError, KeyError, ValueError):
        return None
    fingerprint = fingerprint.decode() if isinstance(fingerprint, bytes) else str(fingerprint)
    return Checkpoint(fingerprint, state, history)


def checkpoint_damage(checkpoint: Checkpoint, expected: dict) -> str | None:
    """Why ``checkpoint`` cannot continue a run whose engine starts from the state ``expected`` (None if it can).

    Every array the engine holds must have its shape in the checkpoint (one the fresh engine holds empty
    grows as it runs: only its dimensions are compared) and be finite; no number may be NaN; the history
    columns must be as long as each other and as the iterations the state counts, and hold no NaN.

    Parameters
    ----------
    checkpoint : Checkpoint
    expected : dict
        ``state()`` of the engine about to run (arrays and scalars by name).

    Returns
    -------
    str or None
        What is wrong, for a note (``/checkpoint/spectrum holds NaN or Inf``).
    """
    for name, value in expected.items():
        if name not in checkpoint.state:
            continue
        saved = np.asarray(checkpoint.state[name])
        if isinstance(value, np.ndarray):
            same = saved.ndim == value.ndim if value.size == 0 else saved.shape == value.shape
            if not same:
                return f"/checkpoint/{name} has shape {saved.shape}, this run's {value.shape}"
            if saved.dtype.kind not in "biufc" or not np.all(np.isfinite(saved)):
                return f"/checkpoint/{name} holds NaN or Inf"
        elif saved.dtype.kind not in "biuf" or saved.ndim != 0 or np.isnan(saved):
            return f"/checkpoint attribute {name} is {saved!r}, not a number"
    lengths = {name: len(np.atleast_1d(values)) for name, values in checkpoint.history.items()}
    counted = checkpoint.state.get("iteration", next(iter(lengths.values()), 0))
    if len(set(lengths.values()) | {int(counted)}) != 1:
        return f"its history holds {lengths} iterations but its state {int(counted)}"
    if any(np.isnan(values).any() for values in checkpoint.history.values()):
        return "its /history holds NaN"
    return None


def remove_checkpoint(path: Path) -> None:
    """Remove the checkpoint at ``path`` if cca wrote it (anything else there is left alone)."""
    if path.is_file() and is_cca_hdf5(path):
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
