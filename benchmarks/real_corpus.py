"""Recorded LED-array sets nobody tuned for: cca's defaults and the peers, read one common way.

Corpus: eight recorded FPM sets (../shared/datasets, ../corpus_extra), each through
``cca ingest`` with its manifest in ``benchmarks/corpus/<set>/manifest.yaml``
(sets that need a conversion a manifest cannot express are rebuilt by
``benchmarks/corpus/rebuild.py`` into ``benchmarks/results/corpus_data/``).
The sets are split once, in :data:`SPLIT`, into a tuning half (what defaults
may be tuned on) and a validation half (what they are judged on).

Tools: cca (``cca reconstruct`` with its defaults, or ``--cca-options`` /
``--cca-config``, timed as a whole command), PtyLab mPIE with pupil recovery
(intensity-weighted pupil steps, βP 0.25 and 0.05) and with a fixed pupil, and
fpm-rs EPRY, each peer in its own environment (``real_peer_worker.py``) after
its forward model has been checked against cca's on the data.

The common reading (``real_model.common_reading``): every object on an integer
upsampling of the frame grid, shifted to align its predicted centre capture
with the measured one, one common pupil map refitted with the object fixed
(40 averaged EPRY steps from A = 1), then the amplitude residual after one
global scale over all / bright-field / dark-field frames, on each frame's
interior. USAF sets: every aligned amplitude registered to a fixed-pupil
reference and the three-bar contrast read per element (boxes in
``benchmarks/corpus/<set>/elements.md``); the resolution limit is the last
element before the first below 0.2. Peers: the best of their snapshots under
this reading, and the time to reach it (start-up included); cca: its final
result and the whole command's time.

Those times come from one run each, maybe hours apart (``--reuse`` keeps a
peer's earlier run), on a machine whose speed may drift. ``--side-by-side N``
times the comparison the acceptance asks for on one footing: cca's whole
command and a fresh run of PtyLab's bar setting up to its best iteration,
interleaved ``N`` times (the order alternating), medians and their ratio. The
bar setting is the fastest PtyLab setting whose residual over all frames is
within :data:`BAR_TOLERANCE` of PtyLab's best.

Usage::

    python benchmarks/real_corpus.py                          # every set, cca defaults + PtyLab + fpm-rs
    python benchmarks/real_corpus.py --half tuning --tools cca --cca-options '{pupil_recovery: none}'
    python benchmarks/real_corpus.py --sets fpm-zuo-usaf11 --reuse      # peers re-read, not re-run
    python benchmarks/real_corpus.py --cca-config my_reconstruct.yaml   # a `reconstruct:` section
    python benchmarks/real_corpus.py --reuse --side-by-side 3          # + interleaved cca / PtyLab timing

Writes ``benchmarks/results/corpus/corpus.json`` (every number, the checks),
``<set>.png`` (each tool's aligned amplitude and phase, one grey scale per
set) and prints one Markdown table. Working files go to
``benchmarks/results/corpus/work/<set>/``.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import math
import os
import platform
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE / "corpus"))

import rebuild
from collect import EXTRA, SOURCES
from real_data import (
    SHARED,
    DatasetSpec,
    Prepared,
    cca_command,
    prepare,
    tool_environment,
)
from real_methods import forward_check, read_cca_recovery, run_peer
from real_model import (
    FrameModel,
    Reading,
    Recovery,
    common_reading,
    fft2c,
    predicted_fields,
)

from cca_cli.metrics import (
    parse_element_table,
    read_bar_elements,
    split_amplitude_residual,
)

CORPUS = HERE / "corpus"
RESULTS = HERE / "results" / "corpus"

#: The split, in one place: what defaults may be tuned on, and what they are judged on.
SPLIT = {
    "fpm-zheng-bloodsmear": "tuning",
    "fpm-usaf-aidukas32": "tuning",
    "fpm-zuo-usaf11": "tuning",
    "fpm-pbnn-bloodcell13": "validation",
    "fpm-euv-sharp-lines81": "validation",
    "fpm-janxu-target100": "validation",
    "fpm-fdpr-ring93": "validation",
    "fpm-elfpie-usaf64": "validation",
}

#: PtyLab mPIE as it works on recorded data (benchmarks/README.md, "PtyLab's pupil recovery").
PEERS = {
    "PtyLab mPIE + pupil βP 0.25": ("ptylab", "ptylab:mPIE",
                                     {"label": "pupil_b025", "weigh_probe_updates_by_intensity": True,
                                      "betaProbe": 0.25}),
    "PtyLab mPIE + pupil βP 0.05": ("ptylab", "ptylab:mPIE",
                                     {"label": "pupil_b005", "weigh_probe_updates_by_intensity": True,
                                      "betaProbe": 0.05}),
    "PtyLab mPIE fixed pupil": ("ptylab", "ptylab:mPIE", {"label": "fixed", "betaProbe": 0.0}),
    "fpm-rs EPRY": ("fpmrs", "fpmrs:epry", {"label": "epry"}),
}
FIXED_PUPIL_REFERENCE = "PtyLab mPIE fixed pupil"
CONTRAST_LIMIT = 0.2
FORWARD_TOLERANCE = 1e-4   # a peer whose forward model differs more from cca's on the data stays out of the table


# ----------------------------------------------------------------------------- the sets

@dataclass(frozen=True)
class CorpusSet:
    """One recorded set of the corpus."""

    name: str

    @property
    def half(self) -> str:
        return SPLIT[self.name]

    @property
    def manifest(self) -> Path:
        return CORPUS / self.name / "manifest.yaml"

    @property
    def elements_file(self) -> Path:
        """USAF element boxes (``parse_element_table`` format), for the USAF sets."""
        return CORPUS / self.name / "elements.md"

    @property
    def readme(self) -> Path:
        """The data folder's README: ``../shared/datasets/<set>`` or, for the sets collected by
        ``corpus/collect.py``, ``../corpus_extra/<set>``."""
        return (EXTRA if self.name in SOURCES else SHARED) / self.name / "README.md"


def margin_px(n: int) -> int:
    """Frame-edge pixels left out of the reading: n/32, within 3–8 px (3 at 32², 4 at 128², 8 at ≥ 256²)."""
    return int(min(8, max(3, n // 32)))


def upsampling(data: Prepared, usaf: bool) -> int:
    """Samples per frame pixel of the object grid.

    It holds the synthetic band and at least 256 samples; on the USAF sets at least 8 per
    frame pixel, so that the finest bars (periods near one frame pixel) are read on smooth
    profiles.
    """
    band = 2 * (np.abs(data.centres).max() + data.radius) + 2
    n = data.intensity.shape[-1]
    return int(max(math.ceil(band / n), math.ceil(256 / n), 8 if usaf else 1))


def bright_field(data: Prepared) -> np.ndarray:
    """Illumination NA at most the objective NA (the EUV set's outer ring sits exactly on the pupil edge)."""
    return data.illumination_na <= data.numerical_aperture * (1 + 1e-9)


def peer_grid(data: Prepared) -> int:
    """The peers' object spectrum size M: every whole-pixel n × n window inside it, a multiple of 32."""
    n = data.intensity.shape[-1]
    need = 2 * int(np.abs(data.windows).max()) + n + 2
    return int(32 * math.ceil(need / 32))


def brightness_check(data: Prepared) -> dict:
    """Do the frames predicted bright-field (illumination NA < NA) hold the brightest frames?"""
    means = data.intensity.reshape(len(data.intensity), -1).mean(axis=1)
    bf = bright_field(data)
    out = {"predicted_bright_field": int(bf.sum()), "frames": int(bf.size)}
    if bf.all():
        out.update(all_bright_field=True, separated=True,
                   mean_spread=float(means.max() / max(means.min(), 1e-30)))
        return out
    brightest = np.argsort(means)[::-1][:int(bf.sum())]
    out.update(min_bright_field_mean=float(means[bf].min()), max_dark_field_mean=float(means[~bf].max()),
               separated=bool(means[bf].min() > means[~bf].max()),
               brightest_are_predicted=int(np.isin(brightest, np.flatnonzero(bf)).sum()))
    return out


def load_set(entry: CorpusSet, workdir: Path, reuse: bool = False) -> tuple[Prepared, FrameModel, int]:
    """Ingest one set (rebuilding a converted copy first if needed); its frame model and object upsampling."""
    if entry.name in SOURCES and not (EXTRA / entry.name).is_dir() and not (reuse and (workdir / "raw.h5").is_file()):
        raise SystemExit(f"{EXTRA / entry.name}: not there; copy the set's files with "
                         f"`python benchmarks/corpus/collect.py --clones DIR {entry.name}` "
                         "(benchmarks/corpus/README.md)")
    try:
        rebuild.ensure(entry.name)
    except (FileNotFoundError, RuntimeError):
        if not (reuse and (workdir / "raw.h5").is_file()):
            raise
    spec = DatasetSpec(entry.name, entry.manifest, entry.readme, peer_hires=0, analysis_grid=0,
                       usaf=entry.elements_file.exists())
    data = prepare(spec, workdir, reuse_ingest=reuse)
    data.spec = replace(spec, peer_hires=peer_grid(data))
    with np.load(data.peer_data) as handle:
        values = {k: handle[k] for k in handle.files}
    values["hires"] = data.spec.peer_hires
    np.savez(data.peer_data, **values)
    with h5py.File(data.raw_h5, "r") as handle:
        weight = np.asarray(handle["/measurements/weight"]) > 0 if "/measurements/weight" in handle else None
    n = data.intensity.shape[-1]
    frames = FrameModel(data.intensity, weight, data.centres, data.radius, bright_field(data), data.centre_index,
                        margin_px(n))
    return data, frames, upsampling(data, spec.usaf)


def data_digest(data: Prepared) -> str:
    """Digest of what every tool is given (frames, weights' source file aside, geometry, peer grid)."""
    h = hashlib.sha256()
    for array in (data.intensity, data.centres, np.array([data.radius, data.wavelength, data.field_width,
                                                          data.spec.peer_hires], np.float64)):
        h.update(np.ascontiguousarray(array).tobytes())
    with h5py.File(data.raw_h5, "r") as handle:
        if "/measurements/weight" in handle:
            h.update(np.ascontiguousarray(handle["/measurements/weight"][()]).tobytes())
        h.update(json.dumps({k: str(v) for k, v in handle["geometry"].attrs.items()}, sort_keys=True).encode())
    return h.hexdigest()


# ----------------------------------------------------------------------------- tools

def cca_config(options: dict | None, config: Path | None) -> dict | None:
    """The `reconstruct` section to pass (None: cca's defaults, no --config)."""
    if options is None and config is None:
        return None
    section = {}
    if config is not None:
        loaded = yaml.safe_load(Path(config).read_text()) or {}
        section = dict(loaded.get("reconstruct", loaded))
    if options is not None:
        section["options"] = {**section.get("options", {}), **options}
    return {"reconstruct": section}


def run_cca(data: Prepared, workdir: Path, config: dict | None) -> tuple[Recovery, dict]:
    """`cca reconstruct` on the ingested set, timed as a whole command (start-up included); always run."""
    text = "" if config is None else yaml.safe_dump(config, sort_keys=False)
    tag = "defaults" if config is None else "cfg_" + hashlib.sha1(text.encode()).hexdigest()[:8]
    recon = workdir / f"cca_{tag}.h5"
    args = [*cca_command(), "reconstruct", str(data.raw_h5), "-o", str(recon), "--force", "--quiet"]
    if config is not None:
        (workdir / f"cca_{tag}.yaml").write_text(text)
        args += ["--config", str(workdir / f"cca_{tag}.yaml")]
    start = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True, env=tool_environment(COLUMNS="200"), check=False)
    wall = time.perf_counter() - start
    (workdir / f"cca_{tag}.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        lines = [line for line in (proc.stderr + proc.stdout).splitlines() if line.strip()]
        raise RuntimeError(lines[-1] if lines else f"exit {proc.returncode}")
    rec, facts = read_cca_recovery(recon, data)
    facts.update(wall_s=wall, command=" ".join(args))
    return rec, facts


def own_residual(rec: Recovery, data: Prepared) -> float:
    """A result's residual with its own pupil (all frames, one scale): cheap, to rank snapshots."""
    measured = np.sqrt(np.clip(data.intensity, 0, None))
    return float(split_amplitude_residual(np.abs(predicted_fields(rec)), measured, bright_field(data)).all)


def candidate_snapshots(snaps: list, data: Prepared, count: int) -> tuple[list[int], list[float]]:
    """Snapshots to read the common way: the best by the peer's own residual, the last, and log-spaced ones."""
    own = [own_residual(rec, data) for _, _, rec in snaps]
    picks = {int(np.argmin(own)), len(snaps) - 1}
    for i in np.unique(np.round(np.geomspace(1, len(snaps), count)).astype(int) - 1):
        picks.add(int(i))
    return sorted(picks), own


def run_peer_tool(label: str, data: Prepared, frames: FrameModel, factor: int, workdir: Path, args) -> dict:
    """One peer setting: run (or reuse), read its snapshots the common way, keep the best."""
    family, method, options = PEERS[label]
    iterations = args.ptylab_iterations if family == "ptylab" else args.fpmrs_iterations
    key = json.dumps({"data": data_digest(data), "method": method, "options": options,
                      "iterations": iterations}, sort_keys=True)
    res = run_peer(method, dict(options, label=f"{options['label']}{iterations}"), iterations, data, workdir,
                   args.timeout, reuse=args.reuse, input_key=hashlib.sha1(key.encode()).hexdigest())
    if res["status"] != "ok":
        return res
    snaps = res["snaps"]
    picks, own = candidate_snapshots(snaps, data, args.snapshot_readings)
    readings = {}
    for i in picks:
        readings[i] = common_reading(snaps[i][2], frames, factor)
    best = min(readings, key=lambda i: readings[i].residual["all"])
    iteration, seconds, _ = snaps[best]
    startup = res.get("startup_s") or 0.0
    seconds_all = np.asarray(res["seconds"])
    return {"status": "ok", "reading": readings[best], "iteration": iteration, "iterations": len(seconds_all),
            "seconds_to_best": startup + seconds, "startup_s": res.get("startup_s"),
            "seconds_whole_run": startup + float(seconds_all[-1]),
            "s_per_iteration": float(np.median(np.diff(np.concatenate([[0.0], seconds_all])))),
            "own_residual_curve": [{"iteration": it, "seconds": s, "own_all": o} for (it, s, _), o in zip(snaps, own)],
            "common_readings": {int(snaps[i][0]): readings[i].residual for i in picks},
            "notes": res["notes"], "reused": res.get("reused", False)}


def timing_check(family: str, data: Prepared, workdir: Path, iterations: int, timeout: float) -> dict:
    """A fresh harness run of the peer and a plain run (``peer_plain_timing.py``) back to back: s/iteration."""
    from real_methods import PEER_PYTHON, peer_available

    label = {"ptylab": "PtyLab mPIE + pupil βP 0.25", "fpmrs": "fpm-rs EPRY"}[family]
    ok, why = peer_available(family)
    if not ok:
        return {"status": "skipped", "reason": why}
    _, method, options = PEERS[label]
    res = run_peer(method, dict(options, label=f"timing{iterations}"), iterations, data, workdir, timeout)
    if res["status"] != "ok":
        return res
    proc = subprocess.run([str(PEER_PYTHON[family]), str(HERE / "peer_plain_timing.py"), family,
                           str(data.peer_data), str(iterations)], capture_output=True, text=True, timeout=timeout,
                          check=False, env=tool_environment())
    line = [x for x in proc.stdout.splitlines() if "s/iteration" in x]
    if proc.returncode != 0 or not line:
        return {"status": "failed", "reason": (proc.stderr or proc.stdout)[-300:]}
    plain = float(line[-1].split(",")[-1].split("s/iteration")[0].strip().split()[-1])
    harness = float(np.median(np.diff(np.concatenate([[0.0], np.asarray(res["seconds"])]))))
    return {"status": "ok", "what": f"{label}, {iterations} iterations, harness then plain",
            "harness_s_per_iteration": harness, "plain_s_per_iteration": plain, "ratio": harness / plain,
            "plain_output": line[-1]}


#: PtyLab settings whose residual over all frames lies this close to PtyLab's best reach "its best" quality.
BAR_TOLERANCE = 0.001


def bar_setting(tools: dict) -> str | None:
    """The PtyLab setting that sets the bar: the fastest to its best among those within :data:`BAR_TOLERANCE`
    of PtyLab's best residual over all frames (None when no PtyLab setting ran)."""
    done = {label: t for label, t in tools.items()
            if label in PEERS and PEERS[label][0] == "ptylab" and t.get("status") == "ok"}
    if not done:
        return None
    best = min(t["residual"]["all"] for t in done.values())
    close = [label for label, t in done.items() if t["residual"]["all"] <= best + BAR_TOLERANCE]
    return min(close, key=lambda label: done[label]["seconds"])


def side_by_side(data: Prepared, workdir: Path, cca_cfg: dict | None, label: str, iteration: int, repeats: int,
                 timeout: float) -> dict:
    """cca's whole command and a fresh run of peer setting ``label`` up to ``iteration``, interleaved.

    The order alternates (cca first in even rounds). A peer's time is its start-up plus its clock at
    the last iteration, as the table's "time to its best".
    """
    _, method, options = PEERS[label]
    cca_s, peer_s = [], []

    def peer() -> None:
        res = run_peer(method, dict(options, label=f"side_by_side{iteration}"), iteration, data, workdir, timeout)
        if res["status"] != "ok":
            raise RuntimeError(f"{label}: {res['status']}: {res.get('reason', '')}")
        peer_s.append((res["startup_s"] or 0.0) + float(res["seconds"][-1]))

    def cca() -> None:
        cca_s.append(run_cca(data, workdir, cca_cfg)[1]["wall_s"])

    for r in range(repeats):
        for step in ((cca, peer) if r % 2 == 0 else (peer, cca)):
            step()
    cca_median, peer_median = float(np.median(cca_s)), float(np.median(peer_s))
    return {"status": "ok", "peer": label, "iteration": iteration, "repeats": repeats, "cca_s": cca_s,
            "peer_s": peer_s, "cca_median_s": cca_median, "peer_median_s": peer_median,
            "ratio": peer_median / cca_median, "load_avg": os.getloadavg()}


# ----------------------------------------------------------------------------- USAF

def element_order(elements) -> list[str]:
    """Element names from coarse to fine."""
    names = sorted({(e.group, e.element) for e in elements})
    return [f"G{g}E{e}" for g, e in names]


def usaf_reading(amplitude: np.ndarray, elements, pixel_m: float, factor: int) -> dict:
    """Contrast per element (the lower of its orientations; NaN → 0), the limit and the last two elements."""
    raw = read_bar_elements(amplitude, elements, pixel_m, factor)
    per_element = {}
    for name in element_order(elements):
        values = [v for k, v in raw.items() if k.split()[0] == name]
        per_element[name] = float(min(0.0 if np.isnan(v) else v for v in values))
    limit = None
    for name, value in per_element.items():
        if value < CONTRAST_LIMIT:
            break
        limit = name
    return {"per_orientation": raw, "per_element": per_element, "limit": limit}


def read_usaf(readings: dict, entry: CorpusSet, data: Prepared, factor: int) -> dict:
    """Register every aligned amplitude to the fixed-pupil reference (flips, integer shift) and read the bars."""
    from bench_real import align

    elements = parse_element_table(entry.elements_file.read_text())
    reference = readings.get(FIXED_PUPIL_REFERENCE)
    out = {}
    pixel_m = data.field_width / data.intensity.shape[-1]
    for label, reading in readings.items():
        amplitude = np.abs(reading.obj)
        how = {"reference": "none (aligned to the centre capture only)"}
        if reference is not None and label != FIXED_PUPIL_REFERENCE:
            moved, how = align(reading.obj, reference.obj, max_shift=2 * factor)
            amplitude = np.abs(moved)
            how["reference"] = FIXED_PUPIL_REFERENCE
        out[label] = {**usaf_reading(amplitude, elements, pixel_m, factor), "registration": how}
    centre = np.sqrt(np.clip(data.intensity[data.centre_index], 0, None)).astype(np.complex128)
    centre_obj = _centre_on_grid(centre, factor)
    out["centre image"] = usaf_reading(np.abs(centre_obj), elements, pixel_m, factor)
    out["elements"] = element_order(elements)
    return out


def _centre_on_grid(centre: np.ndarray, factor: int) -> np.ndarray:
    from real_model import object_on_frame_grid

    n = centre.shape[-1]
    return object_on_frame_grid(Recovery(fft2c(centre), np.ones((1, n, n)), np.zeros(1, int), np.zeros((1, 2), int)),
                                factor)


# ----------------------------------------------------------------------------- one set

def run_set(entry: CorpusSet, args, cca_cfg: dict | None) -> dict:
    workdir = (args.out / "work" / entry.name).resolve()
    print(f"== {entry.name} ({entry.half}): cca ingest ...", flush=True)
    data, frames, factor = load_set(entry, workdir, args.reuse)
    summary = {"set": entry.name, "half": entry.half, "manifest": str(entry.manifest.relative_to(HERE.parent)),
               "frames": list(data.intensity.shape), "bright_field_frames": int(bright_field(data).sum()),
               "pupil_radius_px": data.radius, "upsampling": factor, "margin_px": frames.margin,
               "peer_grid": data.spec.peer_hires, "brightness_check": brightness_check(data),
               "clipped_pixels": 0 if frames.weight is None else int((~frames.weight).sum()), "tools": {}}
    print(f"   {summary['brightness_check']}", flush=True)
    families = sorted({PEERS[t][0] for t in args.tools if t in PEERS})
    if families:
        print(f"   forward-model checks ({', '.join(families)}) ...", flush=True)
        summary["forward_check"] = forward_check(data, families, workdir, args.timeout)
    if families and args.plain_timing:
        print(f"   timing checks ({args.plain_timing} iterations, harness then plain) ...", flush=True)
        summary["timing_check"] = {f: timing_check(f, data, workdir, args.plain_timing, args.timeout)
                                   for f in families}
        print(f"   {summary['timing_check']}", flush=True)
    readings: dict[str, Reading] = {}
    for tool in args.tools:
        print(f"   {tool} ...", flush=True)
        try:
            if tool == "cca":
                rec, facts = run_cca(data, workdir, cca_cfg)
                reading = common_reading(rec, frames, factor)
                entry_out = {"status": "ok", "iterations": facts["iterations"], "seconds": facts["wall_s"],
                             "reconstruct_seconds": facts["seconds"], "engine": facts["engine"],
                             "engine_options": facts["engine_options"], "command": facts["command"],
                             "pupil_source": facts["pupil_source"], "own_residual": own_residual(rec, data)}
            else:
                check = summary.get("forward_check", {}).get(PEERS[tool][0], {})
                if check.get("status") == "ok" and not check["relative_error"] < FORWARD_TOLERANCE:
                    summary["tools"][tool] = {"status": "excluded", "reason": f"forward model off by "
                                              f"{check['relative_error']:.1e} relative (cca's, same spectrum)"}
                    continue
                res = run_peer_tool(tool, data, frames, factor, workdir, args)
                if res["status"] != "ok":
                    summary["tools"][tool] = res
                    print(f"     {res['status']}: {res['reason']}", flush=True)
                    continue
                reading = res.pop("reading")
                entry_out = {**res, "seconds": res["seconds_to_best"]}
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            summary["tools"][tool] = {"status": "failed", "reason": str(exc)[-400:]}
            print(f"     failed: {exc}", flush=True)
            continue
        readings[tool] = reading
        entry_out.update(residual=reading.residual, shift_px=reading.shift_px.tolist(),
                         pupil_gain=float(np.mean(np.abs(reading.pupil))))
        summary["tools"][tool] = entry_out
        r = reading.residual
        print(f"     residual {r['all']:.3f} / {r['bright_field']:.3f} / {r['dark_field']:.3f}, "
              f"{entry_out['seconds']:.1f} s, shift {np.round(reading.shift_px, 2).tolist()} px", flush=True)
    label = bar_setting(summary["tools"])
    if args.side_by_side and "cca" in readings and label is not None:
        iteration = summary["tools"][label]["iteration"]
        print(f"   side by side: cca and {label} to iteration {iteration}, {args.side_by_side} rounds ...", flush=True)
        try:
            sbs = side_by_side(data, workdir, cca_cfg, label, iteration, args.side_by_side, args.timeout)
            print(f"     cca {sbs['cca_median_s']:.1f} s, {label} {sbs['peer_median_s']:.1f} s: "
                  f"{sbs['ratio']:.1f}×", flush=True)
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            sbs = {"status": "failed", "reason": str(exc)[-400:]}
            print(f"     failed: {exc}", flush=True)
        summary["side_by_side"] = sbs
    if entry.elements_file.exists() and readings:
        usaf = read_usaf(readings, entry, data, factor)
        summary["usaf"] = usaf
        for tool in readings:
            summary["tools"][tool]["usaf"] = usaf[tool]
    panels(entry, data, readings, summary, factor, args.out / f"{entry.name}.png")
    return summary


# ----------------------------------------------------------------------------- output

def panels(entry: CorpusSet, data: Prepared, readings: dict, summary: dict, factor: int, path: Path) -> None:
    """Centre image, then each tool's aligned amplitude (one grey scale) over its phase."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centre = _centre_on_grid(np.sqrt(np.clip(data.intensity[data.centre_index], 0, None)).astype(np.complex128),
                             factor)
    items = {"centre image (Fourier-interpolated)": centre, **{k: r.obj for k, r in readings.items()}}
    hi = float(np.percentile(np.concatenate([np.abs(v).ravel() for v in items.values()]), 99.5))
    cols = len(items)
    fig, axes = plt.subplots(2, cols, figsize=(3.2 * cols, 6.6), squeeze=False)
    for j, (name, obj) in enumerate(items.items()):
        axes[0, j].imshow(np.abs(obj), cmap="gray", vmin=0, vmax=hi)
        title = "\n".join(textwrap.wrap(name, 28))
        tool = summary["tools"].get(name)
        if tool is not None:
            r = tool["residual"]
            title += f"\nres {r['all']:.3f} / {r['bright_field']:.3f} / {r['dark_field']:.3f}, {tool['seconds']:.0f} s"
            if "usaf" in tool:
                title += f"\nlimit {tool['usaf']['limit'] or '—'}"
        axes[0, j].set_title(title, fontsize=7)
        if name in readings:
            phase = np.angle(obj * np.exp(-1j * np.angle(np.sum(obj))))
            axes[1, j].imshow(phase, cmap="twilight_shifted", vmin=-np.pi, vmax=np.pi)
        else:
            axes[1, j].set_visible(False)
        for ax in axes[:, j]:
            ax.set_xticks([])
            ax.set_yticks([])
    axes[0, 0].set_ylabel("amplitude (one scale, √counts)", fontsize=8)
    axes[1, min(1, cols - 1)].set_ylabel("phase (−π … π)", fontsize=8)
    fig.suptitle(f"{entry.name} ({entry.half} half): common reading, residual all / BF / DF", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(summary: dict) -> str:
    """One Markdown table, both halves marked."""
    lines = ["| half | set | tool | residual all / BF / DF | USAF limit | last two elements | s | iterations |",
             "|---|---|---|---|---|---|---|---|"]
    for ds in summary["sets"]:
        frames = f"{ds['set']} ({ds['frames'][0]} × {ds['frames'][1]}²)"
        for tool, t in ds["tools"].items():
            if t.get("status") != "ok":
                lines.append(f"| {ds['half']} | {frames} | {tool} | {t['status']}: {t.get('reason', '')[:80]} "
                             f"| | | | |")
                continue
            r = t["residual"]
            limit, last = "—", "—"
            if "usaf" in t:
                limit = t["usaf"]["limit"] or "none"
                names = ds["usaf"]["elements"][-2:]
                last = ", ".join(f"{e} {t['usaf']['per_element'][e]:.2f}" for e in names)
            its = str(t["iterations"]) if tool == "cca" else f"best {t['iteration']} of {t['iterations']}"
            lines.append(f"| {ds['half']} | {frames} | {tool} | {r['all']:.3f} / {r['bright_field']:.3f} / "
                         f"{r['dark_field']:.3f} | {limit} | {last} | {t['seconds']:.1f} | {its} |")
    return "\n".join(lines)


def side_by_side_table(summary: dict) -> str:
    """The interleaved timings, one row per set ('' when none ran)."""
    rows = [ds for ds in summary["sets"] if ds.get("side_by_side", {}).get("status") == "ok"]
    if not rows:
        return ""
    lines = ["| half | set | PtyLab setting (to its best) | cca s (median) | PtyLab s (median) | ratio | rounds |",
             "|---|---|---|---|---|---|---|"]
    for ds in rows:
        t = ds["side_by_side"]
        lines.append(f"| {ds['half']} | {ds['set']} | {t['peer']} (iteration {t['iteration']}) | "
                     f"{t['cca_median_s']:.1f} | {t['peer_median_s']:.1f} | {t['ratio']:.1f}× | {t['repeats']} |")
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(type(x).__name__)


def cca_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=HERE, check=False).stdout.strip()
    except OSError:
        return "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="", help="comma list of set names (default: every set of --half)")
    parser.add_argument("--half", choices=["tuning", "validation", "all"], default="all")
    parser.add_argument("--tools", default="cca," + ",".join(PEERS),
                        help="comma list of: cca, " + ", ".join(PEERS) + "; 'ptylab' / 'fpmrs' name a family")
    parser.add_argument("--reuse", action="store_true",
                        help="reuse peer results whose inputs are unchanged instead of running them again "
                             "(cca always runs), and an earlier ingest of a set whose source files are gone")
    parser.add_argument("--cca-options", default=None, help="YAML mapping passed as reconstruct.options")
    parser.add_argument("--cca-config", type=Path, default=None, help="YAML file with a `reconstruct:` section")
    parser.add_argument("--ptylab-iterations", type=int, default=100)
    parser.add_argument("--fpmrs-iterations", type=int, default=100)
    parser.add_argument("--snapshot-readings", type=int, default=3,
                        help="log-spaced peer snapshots read the common way (plus the best by own residual and the last)")
    parser.add_argument("--plain-timing", type=int, default=0, metavar="N",
                        help="also time N iterations of each peer family in the harness and in a plain run "
                             "(peer_plain_timing.py), back to back")
    parser.add_argument("--side-by-side", type=int, default=0, metavar="N",
                        help="also time cca's whole command and PtyLab's bar setting to its best iteration "
                             "interleaved N times (fresh runs) and report medians and their ratio")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds allowed per peer run")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    names = [s for s in args.sets.split(",") if s] or [s for s, h in SPLIT.items() if args.half in ("all", h)]
    unknown = sorted(set(names) - set(SPLIT))
    if unknown:
        raise SystemExit(f"--sets: unknown {', '.join(unknown)}; known: {', '.join(SPLIT)}")
    tools = []
    for item in (t.strip() for t in args.tools.split(",") if t.strip()):
        family = [k for k, v in PEERS.items() if v[0] == item.lower()]
        if item != "cca" and item not in PEERS and not family:
            raise SystemExit(f"--tools: unknown {item!r}; known: cca, ptylab, fpmrs, " + ", ".join(PEERS))
        tools += family or [item]
    args.tools = list(dict.fromkeys(tools))
    options = None if args.cca_options is None else yaml.safe_load(args.cca_options)
    if options is not None and not isinstance(options, dict):
        raise SystemExit("--cca-options: expected a YAML mapping, e.g. '{pupil_recovery: none}'")
    cca_cfg = cca_config(options, args.cca_config)
    args.out = args.out.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    summary = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "command": " ".join(sys.argv),
               "cca_commit": cca_commit(), "cca_config": cca_cfg, "tools": args.tools,
               "split": SPLIT, "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                                           "load_avg_start": os.getloadavg()}, "sets": []}
    for name in names:
        summary["sets"].append(run_set(CorpusSet(name), args, cca_cfg))
        (args.out / "corpus.json").write_text(json.dumps(summary, indent=1, default=_jsonable))
    summary["machine"]["load_avg_end"] = os.getloadavg()
    summary["wall_s"] = time.perf_counter() - start
    (args.out / "corpus.json").write_text(json.dumps(summary, indent=1, default=_jsonable))
    print(table(summary))
    if args.side_by_side:
        print()
        print(side_by_side_table(summary))
    print(f"wrote {args.out / 'corpus.json'} and one PNG per set beside it ({summary['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
