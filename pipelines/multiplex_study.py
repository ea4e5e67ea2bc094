"""Recipe: the paper's Fig. 13 study of multiplexed illumination, N_mux × T.

Runs simulate → reconstruct → report for every (N_mux, T) point of a
multiplexed config (default configs/study_multiplex.yaml), then writes

    <out>/table.csv, <out>/table.md       one row per point
    <out>/rmse_vs_nmux.png                RMSE of the recovered image vs N_mux, one line per T
    <out>/mtf20_vs_nmux.png               MTF20 (bar width, px) vs N_mux, one line per T
    <out>/recovered_montage.png           recovered intensity per (N_mux, T) and the centre image
    <out>/coverage_montage.png            Fourier coverage map per (N_mux, T), holes in red

Points already computed with the same config are skipped (the runner's
up-to-date check), so an interrupted study resumes.

Usage:
    python pipelines/multiplex_study.py [CONFIG] [--n-mux 1,2,3,5,7,10] [--patterns 1,3] [--out DIR]
                                        [--iterations N] [--points T:NMUX,… ...]
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import h5py
import numpy as np

from cca_cli.config.load import apply_overrides, load_config
from cca_cli.io.multiplex import read_multiplex
from cca_cli.workflows.multiplex import coverage_summary
from cca_cli.stages.runner import run_pipeline

COLUMNS = ("n_mux", "T", "images", "virtual_captures", "coverage_zero_fraction", "coverage_single_fraction",
           "coverage_mean", "rmse_observed", "rmse_recovered", "mtf20_observed_px", "mtf20_recovered_px",
           "iterations", "seconds")


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def run_point(config, n_mux: int, patterns: int, out: Path, iterations: int | None) -> dict:
    overrides = {"multiplex.n_mux": n_mux, "multiplex.patterns": patterns}
    if iterations is not None:
        overrides["reconstruct.iterations"] = iterations
    point = apply_overrides(config, overrides)
    directory = out / f"nmux{n_mux:02d}_T{patterns}"
    run_pipeline(point, directory)
    report = json.loads((directory / "report" / "report.json").read_text())
    row = {"n_mux": n_mux, "T": patterns, "images": report.get("multiplex_measurements"),
           "virtual_captures": report.get("n_images")}
    row.update({k: report.get(k) for k in COLUMNS if k not in row})
    row["directory"] = directory
    return row


def write_table(rows: list[dict], out: Path) -> str:
    with open(out / "table.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)

    def fmt(v):
        if v is None:
            return "—"
        if isinstance(v, float):
            return f"{v:.4f}"
        return str(v)

    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in COLUMNS) + " |" for r in rows]
    text = "\n".join(lines) + "\n"
    (out / "table.md").write_text(text)
    return text


def write_figures(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ts = sorted({r["T"] for r in rows})
    nms = sorted({r["n_mux"] for r in rows})
    for key, label, name in (("rmse_recovered", "RMSE (recovered)", "rmse_vs_nmux.png"),
                             ("mtf20_recovered_px", "MTF20 bar width (px, lower is finer)", "mtf20_vs_nmux.png")):
        fig, ax = plt.subplots(figsize=(5.5, 4), dpi=110)
        for t in ts:
            sel = sorted((r for r in rows if r["T"] == t), key=lambda r: r["n_mux"])
            y = [np.nan if r.get(key) is None else r[key] for r in sel]
            ax.plot([r["n_mux"] for r in sel], y, marker="o", label=f"T = {t}")
        observed = [r.get(key.replace("recovered", "observed")) for r in rows]
        observed = [v for v in observed if v is not None]
        if observed:
            ax.axhline(observed[0], color="gray", ls=":", label="centre camera")
        ax.set_xlabel("N_mux (active sources per pattern)")
        ax.set_ylabel(label)
        ax.legend()
        ax.set_title("Multiplexed illumination, 7x7 cameras x 7x7 sources")
        fig.tight_layout()
        fig.savefig(out / name)
        plt.close(fig)

    lookup = {(r["n_mux"], r["T"]): r for r in rows}
    for kind in ("recovered", "coverage"):
        fig, axes = plt.subplots(len(ts), len(nms) + (kind == "recovered"),
                                 figsize=(2.6 * (len(nms) + 1), 2.8 * len(ts)), dpi=100, squeeze=False)
        for ax in axes.ravel():
            ax.axis("off")
        for i, t in enumerate(ts):
            for j, nm in enumerate(nms):
                row = lookup.get((nm, t))
                if row is None:
                    continue
                ax = axes[i, j]
                with h5py.File(row["directory"] / "recon.h5", "r") as handle:
                    if kind == "recovered":
                        image = np.asarray(handle["/recon/intensity"])
                        ax.imshow(image, cmap="gray", vmin=0, vmax=float(np.percentile(image, 99.5)))
                        ax.set_title(f"N_mux {nm}, T {t}\nRMSE {row['rmse_recovered']:.3f}", fontsize=8)
                        if j == 0:
                            observed = np.asarray(handle["/observed/centre"])
                    else:
                        mux = read_multiplex(handle)
                        size = int(handle["recon"].attrs["hires_size"])
                        _, coverage, band = coverage_summary(mux, size)
                        shown = np.ma.masked_where(coverage == 0, coverage)
                        ax.imshow(shown, cmap="viridis", vmin=1, interpolation="nearest")
                        holes = np.ma.masked_where(~(band & (coverage == 0)), np.ones_like(coverage))
                        ax.imshow(holes, cmap=matplotlib.colors.ListedColormap(["red"]), interpolation="nearest")
                        ax.set_title(f"N_mux {nm}, T {t}\nholes {100 * row['coverage_zero_fraction']:.1f}%",
                                     fontsize=8)
            if kind == "recovered":
                ax = axes[i, -1]
                ax.imshow(observed, cmap="gray", vmin=0, vmax=float(np.percentile(observed, 99.5)))
                ax.set_title("centre camera\n(one source)", fontsize=8)
        fig.tight_layout()
        fig.savefig(out / f"{kind}_montage.png")
        plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default="configs/study_multiplex.yaml")
    parser.add_argument("--n-mux", default="1,2,3,5,7,10", help="comma-separated N_mux values")
    parser.add_argument("--patterns", default="1,3", help="comma-separated T values")
    parser.add_argument("--out", type=Path, default=None, help="study directory (default: run.out_dir)")
    parser.add_argument("--iterations", type=int, default=None, help="override reconstruct.iterations")
    parser.add_argument("--points", action="append", default=None, metavar="T:NMUX,…",
                        help="explicit N_mux list for one T (repeatable), e.g. --points 1:1,2,3 --points 3:1,2; "
                             "replaces --n-mux/--patterns")
    args = parser.parse_args()
    config = load_config(args.config)
    out = args.out or Path(config.run.out_dir or "cca-runs/study_multiplex")
    out.mkdir(parents=True, exist_ok=True)
    if args.points:
        plan = [(int(t), nm) for t, values in (p.split(":", 1) for p in args.points) for nm in _ints(values)]
    else:
        plan = [(t, nm) for t in _ints(args.patterns) for nm in _ints(args.n_mux)]
    rows = []
    for t, nm in plan:
        start = time.perf_counter()
        rows.append(run_point(config, nm, t, out, args.iterations))
        print(f"N_mux {nm:2d}  T {t}: RMSE {rows[-1]['rmse_recovered']:.4f}  MTF20 {rows[-1]['mtf20_recovered_px']}"
              f"  holes {rows[-1]['coverage_zero_fraction']:.3f}  ({time.perf_counter() - start:.0f} s)", flush=True)
    print(write_table(rows, out))
    write_figures(rows, out)


if __name__ == "__main__":
    main()
