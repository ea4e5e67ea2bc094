"""Real LED-array captures through peer FPM codes and every cca engine.

Data: every real LED-array set in ../shared/datasets — the USAF tile
``fpm-usaf-aidukas32`` (441 LEDs, 32², dark level 16) and the green blood smear
``fpm-zheng-bloodsmear`` (225 LEDs, 128²; values read as amplitudes, as
``configs/bloodsmear_green.yaml`` does, and as intensities). Each set goes
through ``cca ingest`` with the manifest a user writes from its README; the
ingested measurements are what every method fits.

Methods: PtyLab mPIE with a fixed pupil and with pupil recovery, fpm-rs EPRY
(pupil recovery), and every registered cca engine run through
``cca reconstruct`` with its defaults (plus ``--cca-options``).

Before any number counts, each peer's forward operator is checked against
cca's on the data's geometry (same spectrum, same disc pupil, whole-pixel
centres), and each peer's result is converted into one common representation
(object spectrum, pupil(s), per-capture windows: ``real_model.py``) whose
predictions are checked against the peer's own.

Per method and data set: amplitude residual with one global scale over all /
bright-field / dark-field frames (``cca_cli.metrics.split_amplitude_residual``),
sharpness, the three-bar contrast of the USAF elements in the README's boxes
(``cca_cli.metrics.read_bar_elements``) after aligning every amplitude to the
centre image, s/iteration, total seconds, seconds to reach PtyLab mPIE +
pupil's residual; residual-vs-time curves, PNG panels and a JSON.

Usage::

    python benchmarks/bench_real.py [--datasets usaf_aidukas32,bloodsmear_green_amplitude,bloodsmear_green_intensity]
        [--peers ptylab,fpmrs] [--engines altmin,momentum] [--cca-options 'momentum:{pupil_recovery: shared}']
        [--ptylab-iterations 50,200] [--fpmrs-iterations 50] [--out benchmarks/results/real.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from real_data import DATASETS, Prepared, prepare  # noqa: E402
from real_methods import (forward_check, relative_error, run_cca_engine,  # noqa: E402
                          run_peer)
from real_model import Recovery, fft2c, ifft2c, predicted_fields  # noqa: E402

from cca_cli.engines.registry import engine_names  # noqa: E402
from cca_cli.metrics import parse_element_table, read_bar_elements, split_amplitude_residual  # noqa: E402
from cca_cli.metrics.sharpness import rms_frequency, spectral_energy_beyond  # noqa: E402

#: PtyLab mPIE set up as it works on these data (see benchmarks/README.md, "PtyLab's pupil recovery").
PTYLAB_FIXED = {"label": "fixed", "betaProbe": 0.0}
PTYLAB_PUPIL = [{"label": "pupil_b025", "weigh_probe_updates_by_intensity": True, "betaProbe": 0.25},
                {"label": "pupil_b005", "weigh_probe_updates_by_intensity": True, "betaProbe": 0.05}]
FPMRS_EPRY = {"label": "pupil"}


# ----------------------------------------------------------------------------- evaluation

def residuals(rec: Recovery, data: Prepared) -> dict:
    """Split residual of one result, without and (when it has them) with its brightness factors."""
    measured = np.sqrt(np.clip(data.intensity, 0, None))
    out = {}
    for with_brightness in ([False, True] if rec.brightness is not None else [False]):
        r = split_amplitude_residual(np.abs(predicted_fields(rec, brightness=with_brightness)), measured,
                                     data.bright_field)
        out["with_brightness" if with_brightness else "plain"] = {
            "all": r.all, "bright_field": r.bright_field, "dark_field": r.dark_field, "scale": r.scale}
    return out


def pupil_summary(pupil: np.ndarray, radius: float) -> dict:
    """What a recovered pupil looks like: amplitude inside/outside the disc and a low-order Zernike fit.

    The phase (relative to the disc centre) is fitted, weighted by the amplitude, with RMS-normalised
    modes over the disc of radius R: tilts (→ image shift in low-res pixels), defocus √3(2ρ²−1),
    astigmatism √6ρ²cos2θ, √6ρ²sin2θ; coefficients in waves.
    """
    n = pupil.shape[-1]
    yy, xx = np.mgrid[:n, :n] - n // 2
    inside = np.hypot(yy, xx) <= radius
    amp = np.abs(pupil)
    p = pupil[inside] * np.exp(-1j * np.angle(pupil[n // 2, n // 2]))
    y, x = yy[inside] / radius, xx[inside] / radius
    r2 = x * x + y * y
    basis = np.stack([np.ones_like(x), 2 * y, 2 * x, np.sqrt(3) * (2 * r2 - 1), np.sqrt(6) * (x * x - y * y),
                      np.sqrt(6) * 2 * x * y], 1)
    w = np.abs(p) / max(float(np.abs(p).max()), 1e-30)
    coef, *_ = np.linalg.lstsq(basis * w[:, None], np.angle(p) * w, rcond=None)
    waves = coef / (2 * np.pi)
    fitted = basis @ coef
    resid = np.angle(p * np.exp(-1j * fitted))
    # tilt phase 2·a·y/R radians shifts the image by a·n/(π R) pixels
    return {"amplitude_inside": {"mean": float(amp[inside].mean()), "std": float(amp[inside].std()),
                                 "min": float(amp[inside].min()), "max": float(amp[inside].max())},
            "amplitude_outside_max": float(amp[~inside].max()) if (~inside).any() else 0.0,
            "phase_rms_rad": float(np.sqrt(np.average(np.angle(p) ** 2, weights=w))),
            "zernike_waves": {"tilt_y": float(waves[1]), "tilt_x": float(waves[2]), "defocus": float(waves[3]),
                              "astigmatism_0": float(waves[4]), "astigmatism_45": float(waves[5])},
            "image_shift_lowres_px": [float(coef[1] * n / (np.pi * radius)), float(coef[2] * n / (np.pi * radius))],
            "phase_rms_beyond_fit_rad": float(np.sqrt(np.average(resid ** 2, weights=w)))}


def resample(spectrum: np.ndarray, size: int) -> np.ndarray:
    """Object on a size x size grid: the centred spectrum zero-padded or cropped about DC."""
    m = spectrum.shape[-1]
    out = np.zeros((size, size), np.complex128)
    if m <= size:
        lo = size // 2 - m // 2
        out[lo:lo + m, lo:lo + m] = spectrum
    else:
        lo = m // 2 - size // 2
        out[:] = spectrum[lo:lo + size, lo:lo + size]
    return ifft2c(out) * (size / m)


def _dihedral(image: np.ndarray, k: int) -> np.ndarray:
    out = np.rot90(image, k % 4)
    return out.T if k >= 4 else out


def align(obj: np.ndarray, reference: np.ndarray, max_shift: int) -> tuple[np.ndarray, dict]:
    """Flip/transpose and whole-pixel circular shift (within ±max_shift) that best match |obj| to |reference|."""
    ref = np.abs(reference) - np.abs(reference).mean()
    ref_f = np.conj(np.fft.fft2(ref))
    best = None
    for k in range(8):
        a = np.abs(_dihedral(obj, k))
        corr = np.fft.ifft2(np.fft.fft2(a - a.mean()) * ref_f).real
        corr = corr / (np.linalg.norm(a - a.mean()) * np.linalg.norm(ref) + 1e-30)
        shifts = (np.arange(corr.shape[0]) + corr.shape[0] // 2) % corr.shape[0] - corr.shape[0] // 2
        allowed = (np.abs(shifts)[:, None] <= max_shift) & (np.abs(shifts)[None, :] <= max_shift)
        masked = np.where(allowed, corr, -np.inf)
        idx = np.unravel_index(int(np.argmax(masked)), masked.shape)
        if best is None or masked[idx] > best[0]:
            best = (float(masked[idx]), k, (-int(shifts[idx[0]]), -int(shifts[idx[1]])))
    score, k, shift = best
    return np.roll(_dihedral(obj, k), shift, axis=(0, 1)), {"dihedral": k, "shift_px": list(shift),
                                                             "correlation": score}


def reference_method(results: dict) -> str | None:
    """The result every amplitude is aligned to: a fixed-pupil recovery, whose frame is the frames' own.

    cca altmin (fixed disc pupil, nominal centres, the README's sign) first, else a PtyLab fixed-pupil run.
    A pupil that is recovered may carry a linear phase, which shifts the image; a blurred centre image is
    too soft a reference for sub-pixel boxes.
    """
    ok = [k for k, v in results.items() if v.get("status") == "ok"]
    for label in ok:
        if label == "cca altmin":
            return label
    return next((k for k in ok if k.startswith("PtyLab mPIE fixed pupil")), None)


def evaluate_images(results: dict, data: Prepared) -> dict:
    """Objects on the analysis grid aligned to a common reference; sharpness and bar readings."""
    grid = data.spec.analysis_grid
    n = data.intensity.shape[-1]
    upsampling = grid / n
    centre_amp = np.sqrt(np.clip(data.intensity[data.centre_index], 0, None)).astype(np.complex128)
    centre = resample(fft2c(centre_amp), grid).real
    pixel_m = data.field_width / grid
    elements = parse_element_table(data.spec.readme.read_text()) if data.spec.usaf else []
    objects = {}
    for name, res in results.items():
        if res.get("status") != "ok":
            continue
        rec = res["final"]
        scale = res["residual"]["plain"]["scale"]
        # in units of √(measured intensity): |ψ| = |object|·|P|·M/n for centred orthonormal transforms;
        # a recovered pupil's mean amplitude over the disc is moved into the object for display
        window = rec.n  # the frames' size, or the padded grid's for a recovery with a guard band
        radius = data.radius * window / n
        yy, xx = np.mgrid[:window, :window] - window // 2
        disc = np.hypot(yy, xx) <= radius
        gain = float(np.mean(np.abs(np.asarray(rec.pupils))[:, disc]))
        factor = grid // n
        obj = resample(np.asarray(rec.spectrum, np.complex128), factor * window)
        if rec.crop_yxhw is not None:  # the frames' part of the padded field, sampled as the others
            y0, x0, _, _ = rec.crop_yxhw
            obj = obj[factor * y0:factor * y0 + grid, factor * x0:factor * x0 + grid]
        objects[name] = obj * scale * gain * (rec.spectrum.shape[-1] / window)
    ref_name = reference_method(results)
    reference = objects[ref_name] if ref_name else centre
    images = {"centre image": centre}
    out = {}
    centre_sharp = rms_frequency(centre ** 2, pixel_m)
    for name, obj in objects.items():
        if name == ref_name:
            how = {"dihedral": 0, "shift_px": [0, 0], "correlation": 1.0, "reference": True}
        else:
            obj, how = align(obj, reference, max_shift=int(round(grid * 0.2)))
        images[name] = obj
        intensity = np.abs(obj) ** 2
        entry = {"alignment": how,
                 "sharpness": {"rms_frequency_lp_per_mm": rms_frequency(intensity, pixel_m) / 1e3,
                               "gain_over_centre": rms_frequency(intensity, pixel_m) / centre_sharp,
                               "energy_beyond_2R": spectral_energy_beyond(intensity, 2 * data.radius)}}
        if elements:
            entry["bars"] = read_bar_elements(np.abs(obj), elements, data.field_width / n, upsampling)
        out[name] = entry
    _, centre_how = align(centre.astype(np.complex128), reference, max_shift=int(round(grid * 0.2)))
    summary = {"centre": {"sharpness": {"rms_frequency_lp_per_mm": centre_sharp / 1e3,
                                        "energy_beyond_2R": spectral_energy_beyond(centre ** 2, 2 * data.radius)},
                          "alignment_to_reference": centre_how}}
    if elements:
        summary["centre"]["bars"] = read_bar_elements(np.abs(centre), elements, data.field_width / n, upsampling)
    return {"methods": out, **summary, "images": images, "upsampling": upsampling,
            "alignment_reference": ref_name or "centre image"}


def conversion_check(res: dict, data: Prepared) -> dict:
    """The common representation of a peer's final state against the peer's own prediction of it."""
    rec = res["final"]
    fields = predicted_fields(rec)
    if res.get("own_intensity") is not None:
        err, scale = relative_error(np.abs(fields) ** 2, res["own_intensity"])
        return {"what": "peer's own predicted intensities of its final object and pupil", "relative_error": err,
                "scale": scale}
    if res.get("own_loss") is not None:
        n, m = data.intensity.shape[-1], rec.spectrum.shape[-1]
        mine = float(np.mean((np.abs(fields) * n / m - np.sqrt(np.clip(data.intensity, 0, None))) ** 2))
        return {"what": "fpm-rs's own amplitude_mse loss of its final state (a pass with vanishing steps)",
                "relative_error": abs(mine - res["own_loss"]) / res["own_loss"], "peer": res["own_loss"],
                "common": mine}
    return {"what": "none available"}


def curve(res: dict, data: Prepared) -> list[dict]:
    out = []
    for iteration, seconds, rec in res["snaps"]:
        r = residuals(rec, data)["plain"]
        out.append({"iteration": iteration, "seconds": seconds, **r})
    return out


# ----------------------------------------------------------------------------- one data set

def parse_cca_options(items: list[str]) -> dict:
    """``engine:{yaml mapping}`` arguments → {engine: options}."""
    out: dict[str, dict] = {}
    for item in items:
        engine, _, text = item.partition(":")
        value = yaml.safe_load(text) if text.strip() else {}
        if not isinstance(value, dict):
            raise SystemExit(f"--cca-options {item!r}: expected ENGINE:{{key: value, ...}}")
        out.setdefault(engine.strip(), {}).update(value)
    return out


def run_dataset(name: str, args, cca_options: dict) -> tuple[dict, dict]:
    spec = DATASETS[name]
    workdir = (args.out.parent / "real_work" / name).resolve()
    print(f"== {name}: cca ingest ...", flush=True)
    data = prepare(spec, workdir)
    families = [p for p in args.peers.split(",") if p]
    print(f"   forward-model checks ({', '.join(families) or 'none'}) ...", flush=True)
    check = forward_check(data, families, workdir, args.timeout)
    results: dict[str, dict] = {}
    peer_runs = []
    if "ptylab" in families:
        longest = max(args.ptylab_iterations)
        peer_runs.append((f"PtyLab mPIE fixed pupil ({longest} its)", "ptylab:mPIE", PTYLAB_FIXED, longest))
        for options in PTYLAB_PUPIL:
            for its in args.ptylab_iterations:
                peer_runs.append((f"PtyLab mPIE + pupil, betaProbe {options['betaProbe']} ({its} its)", "ptylab:mPIE",
                                  options, its))
    if "fpmrs" in families:
        for its in args.fpmrs_iterations:
            peer_runs.append((f"fpm-rs EPRY + pupil ({its} its)", "fpmrs:epry", FPMRS_EPRY, its))
    for label, method, options, its in peer_runs:
        print(f"   {label} ...", flush=True)
        res = run_peer(method, dict(options, label=f"{options['label']}{its}"), its, data, workdir, args.timeout,
                       reuse=args.reuse)
        if res["status"] != "ok":
            print(f"     {res['status']}: {res['reason']}", flush=True)
            results[label] = res
            continue
        res["final"] = res["snaps"][-1][2]
        res["residual"] = residuals(res["final"], data)
        res["conversion_check"] = conversion_check(res, data)
        res["pupil"] = pupil_summary(np.asarray(res["final"].pupils[0]), data.radius)
        res["curve"] = curve(res, data)
        sec = np.asarray(res["seconds"])
        res["s_per_iteration"] = float(np.median(np.diff(np.concatenate([[0.0], sec]))))
        res["total_s"] = float(sec[-1])
        res["iterations"] = len(sec)
        print(f"     residual all/BF/DF {res['residual']['plain']['all']:.3f}/"
              f"{res['residual']['plain']['bright_field']:.3f}/{res['residual']['plain']['dark_field']:.3f}, "
              f"{res['s_per_iteration']:.3f} s/it, conversion check {res['conversion_check'].get('relative_error')}",
              flush=True)
        results[label] = res
    for engine in args.engines:
        options = cca_options.get(engine, {})
        label = f"cca {engine}" + (f" {json.dumps(options)}" if options else "")
        print(f"   {label} (cca reconstruct, defaults) ...", flush=True)
        try:
            rec, facts = run_cca_engine(engine, options, data, workdir, reuse=args.reuse)
        except RuntimeError as exc:
            print(f"     failed: {exc}", flush=True)
            results[label] = {"status": "failed", "reason": str(exc)}
            continue
        res = {"status": "ok", "final": rec, "facts": facts, "residual": residuals(rec, data)}
        if rec.pupils.shape[0] == 1:
            res["pupil"] = pupil_summary(np.asarray(rec.pupils[0]), data.radius)
        res["iterations"] = facts["iterations"]
        res["total_s"] = facts["seconds"]
        hist = np.asarray(facts["history"].get("seconds", []))
        res["s_per_iteration"] = float(np.median(np.diff(np.concatenate([[0.0], hist])))) if hist.size else None
        points = []
        for its in args.cca_checkpoints:
            if its >= facts["iterations"]:
                continue
            r_rec, r_facts = run_cca_engine(engine, options, data, workdir, iterations=its, reuse=args.reuse)
            points.append({"iteration": r_facts["iterations"], "seconds": r_facts["seconds"],
                           **residuals(r_rec, data)["plain"]})
        points.append({"iteration": facts["iterations"], "seconds": facts["seconds"], **res["residual"]["plain"]})
        res["curve"] = points
        res["notes"] = f"{facts['command']}; pupil: {facts['pupil_source']}; calibration saved: {facts['calibration']}"
        print(f"     {facts['iterations']} its in {facts['seconds']:.1f} s; residual all/BF/DF "
              f"{res['residual']['plain']['all']:.3f}/{res['residual']['plain']['bright_field']:.3f}/"
              f"{res['residual']['plain']['dark_field']:.3f}", flush=True)
        results[label] = res
    # the target: PtyLab mPIE + pupil's best residual (all frames) over its settings and run lengths
    pupil_runs = {k: v["residual"]["plain"]["all"] for k, v in results.items()
                  if k.startswith("PtyLab mPIE + pupil") and v["status"] == "ok"}
    target_name = min(pupil_runs, key=pupil_runs.get) if pupil_runs else None
    target = pupil_runs[target_name] if target_name else None
    for res in results.values():
        if res.get("status") != "ok":
            continue
        hit = [p for p in res["curve"] if target is not None and p["all"] <= target]
        res["seconds_to_target"] = hit[0]["seconds"] if hit else None
    images = evaluate_images(results, data)
    panels(images, results, data, args.out.parent / f"real_{name}.png")
    curves_plot(results, target, args.out.parent / f"real_{name}_curves.png", name)
    summary = {"dataset": name, "manifest": str(spec.manifest.relative_to(HERE.parent)),
               "manifest_used": str(data.manifest_used), "manifest_note": data.manifest_note,
               "frames": list(data.intensity.shape), "bright_field_frames": int(data.bright_field.sum()),
               "pupil_radius_px": data.radius, "forward_check": check,
               "target": {"method": target_name, "residual_all": target},
               "centre": images["centre"], "alignment_reference": images["alignment_reference"], "methods": {}}
    for label, res in results.items():
        entry = {k: v for k, v in res.items() if k not in ("final", "snaps", "own_intensity", "seconds")}
        entry.update(images["methods"].get(label, {}))
        summary["methods"][label] = entry
    return summary, images


# ----------------------------------------------------------------------------- output

def panels(images: dict, results: dict, data: Prepared, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    items = images["images"]
    names = list(items)
    amps = {k: np.abs(v) for k, v in items.items()}
    hi = float(np.percentile(np.concatenate([a.ravel() for a in amps.values()]), 99.5))
    fig, axes = plt.subplots(2, len(names), figsize=(2.6 * len(names), 6.0), squeeze=False)
    for j, name in enumerate(names):
        axes[0, j].imshow(amps[name], cmap="gray", vmin=0, vmax=hi)
        title = "\n".join(textwrap.wrap(name, 30))
        res = results.get(name)
        if res is not None and res.get("status") == "ok":
            r = res["residual"]["plain"]
            title += f"\nres {r['all']:.3f} / {r['bright_field']:.3f} / {r['dark_field']:.3f}"
        axes[0, j].set_title(title, fontsize=7)
        obj = items[name]
        if np.iscomplexobj(obj):
            phase = np.angle(obj * np.exp(-1j * np.angle(np.sum(obj))))
            axes[1, j].imshow(phase, cmap="twilight_shifted", vmin=-np.pi, vmax=np.pi)
        else:
            axes[1, j].set_visible(False)
        for ax in axes[:, j]:
            ax.set_xticks([])
            ax.set_yticks([])
    axes[0, 0].set_ylabel("amplitude (same scale)", fontsize=8)
    axes[1, min(1, len(names) - 1)].set_ylabel("phase (−π … π)", fontsize=8)
    fig.suptitle(f"{data.spec.name}: residual all / bright field / dark field (one global scale)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def curves_plot(results: dict, target, path: Path, name: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label, res in results.items():
        if res.get("status") != "ok":
            continue
        c = res["curve"]
        ax.plot([p["seconds"] for p in c], [p["all"] for p in c], "-" if label.startswith("cca") else "--",
                marker=".", label=label)
    if target is not None:
        ax.axhline(target, color="grey", lw=0.8, ls=":", label="PtyLab mPIE + pupil (final)")
    ax.set(xscale="log", xlabel="wall time (s)", ylabel="amplitude residual, all frames (one scale)", title=name)
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(summary: dict) -> str:
    elements = []
    lines = []
    for ds in summary["datasets"]:
        lines.append(f"\n{ds['dataset']} ({ds['frames'][0]} frames of {ds['frames'][1]}², "
                     f"{ds['bright_field_frames']} bright-field)")
        bars = ds["centre"].get("bars")
        elements = ["G8E4 col", "G8E4 row", "G9E1 col", "G9E1 row", "G9E2 col", "G9E3 col"] if bars else []
        head = "| method | residual all / BF / DF | with brightness | " + " | ".join(elements) + \
               (" | " if elements else "") + "sharpness gain | s/iteration | total s | s to target |"
        lines += [head, "|" + "---|" * (7 + len(elements))]
        for label, m in ds["methods"].items():
            if m.get("status") != "ok":
                lines.append(f"| {label} | {m['status']}: {m.get('reason', '')[:120]} |" + " |" * (5 + len(elements)))
                continue
            r = m["residual"]["plain"]
            wb = m["residual"].get("with_brightness")
            wbs = f"{wb['all']:.3f} / {wb['bright_field']:.3f} / {wb['dark_field']:.3f}" if wb else "—"
            cells = [f"{m['bars'][e]:.2f}" if not np.isnan(m["bars"][e]) else "–" for e in elements] if bars else []
            spi = m.get("s_per_iteration")
            tt = m.get("seconds_to_target")
            lines.append(f"| {label} | {r['all']:.3f} / {r['bright_field']:.3f} / {r['dark_field']:.3f} | {wbs} | "
                         + " | ".join(cells) + (" | " if cells else "")
                         + f"{m['sharpness']['gain_over_centre']:.2f} | {'—' if spi is None else f'{spi:.4f}'} | "
                         f"{m['total_s']:.2f} | {'—' if tt is None else f'{tt:.2f}'} |")
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, Recovery):
        return None
    raise TypeError(type(x).__name__)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", default=",".join(DATASETS))
    parser.add_argument("--peers", default="ptylab,fpmrs", help="comma list of ptylab, fpmrs ('' for none)")
    parser.add_argument("--engines", default=",".join(engine_names()), help="cca engines (default: every registered one)")
    parser.add_argument("--cca-options", action="append", default=[],
                        help="ENGINE:{yaml mapping}, e.g. 'momentum:{pupil_recovery: shared}' (repeatable)")
    parser.add_argument("--cca-checkpoints", default="1,3,10,30,100,300",
                        help="extra cca runs capped at these iteration counts, for the residual-vs-time curve")
    parser.add_argument("--ptylab-iterations", default="50,200")
    parser.add_argument("--fpmrs-iterations", default="50")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "real.json")
    parser.add_argument("--reuse", action="store_true",
                        help="read results an earlier run left in results/real_work instead of running again "
                             "(re-evaluation only; timings are the earlier run's)")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds allowed per peer run")
    args = parser.parse_args()
    args.engines = [e for e in args.engines.split(",") if e]
    args.cca_checkpoints = [int(v) for v in args.cca_checkpoints.split(",") if v]
    args.ptylab_iterations = [int(v) for v in args.ptylab_iterations.split(",") if v]
    args.fpmrs_iterations = [int(v) for v in args.fpmrs_iterations.split(",") if v]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cca_options = parse_cca_options(args.cca_options)
    start = time.perf_counter()
    summary = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
               "command": " ".join(sys.argv),
               "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_avg_start": os.getloadavg()},
               "cca_options": cca_options, "datasets": []}
    for name in [d for d in args.datasets.split(",") if d]:
        ds, _ = run_dataset(name, args, cca_options)
        summary["datasets"].append(ds)
        args.out.write_text(json.dumps(summary, indent=1, default=_jsonable))
    summary["machine"]["load_avg_end"] = os.getloadavg()
    summary["wall_s"] = time.perf_counter() - start
    args.out.write_text(json.dumps(summary, indent=1, default=_jsonable))
    print(table(summary))
    print(f"wrote {args.out} and real_*.png beside it")


if __name__ == "__main__":
    main()
