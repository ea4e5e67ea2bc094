"""The tiny base config of the sweep tests."""

from __future__ import annotations

from cca_cli.config.load import parse_config


def tiny_config(**sections):
    """A 64-px chart, 3x3 grid, band storage, few iterations: each point runs in well under a second."""
    data = {
        "scene": {"kind": "resolution_chart", "size_px": 64, "field_width_m": 64 * 125e-6, "widths_px": [4, 3, 2, 1]},
        "array": {"grid": 3, "overlap": 0.61},
        "noise": {"model": "gaussian", "snr_db": 30, "seed": 10},
        "simulate": {"store": "band"},
        "reconstruct": {"iterations": 15, "tol": 0},
        "report": {"figures": False},
    }
    for name, values in sections.items():
        data[name] = {**data.get(name, {}), **values}
    return parse_config(data)
