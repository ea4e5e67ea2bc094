"""Stage `report`: recon.h5 → report/ (report.json and PNG figures)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReportSection
from cca_cli.io.geometry import read_geometry
from cca_cli.io.h5 import Provenance, atomic_path, check_output, open_input, require
from cca_cli.report.summary import ReportInputs, summarize
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent
from cca_cli.stages.scene import table_to_bars

__all__ = ["SECTIONS", "REPORT_JSON", "run"]

SECTIONS = ("report",)
REPORT_JSON = "report.json"


def run(recon_path: Path, section: ReportSection, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> dict:
    """Compute the report of ``recon_path`` and write it (atomically) as directory ``output``."""
    check_output(output, force=force)
    with open_input(recon_path, stage="reconstruct") as handle:
        geometry = read_geometry(handle)
        spectrum = np.asarray(require(handle, "/recon/spectrum", ndim=2))
        obj = np.asarray(require(handle, "/recon/object", ndim=2))
        recovered = np.asarray(require(handle, "/recon/intensity", ndim=2))
        observed = np.asarray(require(handle, "/observed/centre", ndim=2))
        residual = np.asarray(handle["/history/residual"])
        change = np.asarray(handle["/history/change"])
        truth_obj = np.asarray(handle["/truth/object"]) if "/truth/object" in handle else None
        bars = table_to_bars(np.asarray(handle["/truth/bars"])) if "/truth/bars" in handle else ()
        attrs = dict(handle["recon"].attrs)
    truth = None if truth_obj is None else (np.abs(truth_obj) ** 2).astype(np.float32)
    inputs = ReportInputs(geometry=geometry, observed=observed, recovered=recovered, truth=truth, bars=bars,
                          engine=str(attrs.get("engine")), iterations=int(attrs.get("iterations", 0)),
                          seconds=float(attrs.get("seconds", 0.0)), hires_size=int(attrs.get("hires_size")),
                          lowres_size=int(attrs.get("lowres_size")))
    summary = summarize(inputs, threshold=section.mtf_threshold)
    progress(ProgressEvent("report", "metrics", 1, 2))
    with atomic_path(output, force=True) as tmp:
        tmp.mkdir(parents=True)
        if section.figures:
            from cca_cli.report.figures import write_figures

            figures = write_figures(tmp, observed=observed, recovered_object=obj, spectrum=spectrum,
                                    pupil_centres_px=geometry.spectrum_centres_yx_px,
                                    pupil_radius_px=geometry.pupil_radius_px, field_width_m=geometry.field_width_m,
                                    residual=residual, change=change, summary=summary, truth=truth)
            summary["figures"] = [p.name for p in figures]
        document = dict(summary)
        document["provenance"] = {k: (v if isinstance(v, str) else str(v)) for k, v in provenance.items()}
        (tmp / REPORT_JSON).write_text(json.dumps(document, indent=2))
        if output.exists():
            import shutil

            shutil.rmtree(output)
    progress(ProgressEvent("report", "figures", 2, 2))
    return summary
