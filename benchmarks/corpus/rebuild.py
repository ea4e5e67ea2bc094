"""Rebuild the converted copies of the corpus sets that a manifest cannot read as they are.

Three sets need a conversion that a `cca ingest` manifest cannot express:

* ``fpm-fdpr-ring93`` — 1024² frames: the centred 256² crop (rows and columns
  384:640) of every frame, written unchanged as 8-bit TIFFs, with a table
  ``images.csv`` (``path,kx_norm,ky_norm``; the angles are those of the frame
  centre, which is the crop's centre).
* ``fpm-euv-sharp-lines81`` — every frame was scaled to its own maximum
  upstream: each frame is rescaled to the mean of all frames' means (all 81 are
  bright-field, so their mean intensities should agree) and the centred 256²
  crop (rows and columns 38:294 of 332²) is kept, as ``frames.mat`` (variable
  ``frames``, (256, 256, 81) float32) with ``illumination.csv``, whose sines are
  0.9 × the README's (``EUV_ILLUMINATION_SCALE``): at the nominal scale every
  recovery shows a horizontal grid artefact and cca's data residual is 0.139;
  at 0.8 / 0.85 / 0.9 / 0.95 / 1.1 × it is 0.097 / 0.094 / 0.082 / 0.206 / 0.164,
  and the lines come out clean at 0.85–0.9 (the σ coordinates of the SHARP
  illuminator are evidently not in units of the 0.0825 NA this set assumes).

* ``fpm-janxu-target100`` — 300² frames whose chart fills a narrow strip: the
  centred 128² crop (rows and columns 86:214) of the 3-exposure stack
  (``FPM_RawData_3HDR.mat``), still amplitudes, as ``frames.mat`` (variable
  ``imlow_HDR``) with ``illumination.csv``. At 300² the peers' object grid would
  be 1024² or more (NA 0.15 with illumination up to NA 0.57), too slow for a
  benchmark on 2 cores; the crop holds the 190–270 lp/mm groups.

The copies go to ``benchmarks/results/corpus_data/<set>/`` (git-ignored) and are
made from the upstream files in ``../corpus_extra/<set>/`` beside the checkout
(``collect.py`` copies them there from clones of the source repositories) and
the illumination table beside each manifest (``benchmarks/corpus/<set>/illumination.csv``);
nothing is written into the repository.

Usage::

    python benchmarks/corpus/rebuild.py [--force] [SET ...]     # default: every set that needs one
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
OUT = ROOT / "benchmarks" / "results" / "corpus_data"
sys.path.insert(0, str(HERE))

from collect import EXTRA  # noqa: E402  (the folder beside the checkout that holds the upstream files)

FDPR_CROP = (384, 640)   # rows = columns, of 1024
EUV_CROP = (38, 294)     # rows = columns, of 332
JANXU_CROP = (86, 214)   # rows = columns, of 300
EUV_ILLUMINATION_SCALE = 0.9


def _read_table(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _stamp(folder: Path, what: dict) -> None:
    (folder / "rebuilt.json").write_text(json.dumps(what, indent=1))


def rebuild_fdpr(out: Path) -> Path:
    """Centred 256² crops of the ring-LED set's 1024² frames (8-bit TIFFs, unchanged values).

    Parameters
    ----------
    out : Path
        Folder to write (created).

    Returns
    -------
    Path
        The table ``images.csv`` the manifest names.
    """
    from PIL import Image

    src = EXTRA / "fpm-fdpr-ring93"
    lo, hi = FDPR_CROP
    (out / "frames").mkdir(parents=True, exist_ok=True)
    rows = _read_table(HERE / src.name / "illumination.csv")
    table = out / "images.csv"
    with open(table, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["path", "kx_norm", "ky_norm"])
        for row in rows:
            frame = np.asarray(Image.open(src / row["path"]))
            if frame.shape != (1024, 1024) or frame.dtype != np.uint8:
                raise SystemExit(f"{src / row['path']}: expected a 1024² uint8 frame, got {frame.shape} {frame.dtype}")
            name = f"frames/{int(row['image_index']):03d}.tif"
            Image.fromarray(np.ascontiguousarray(frame[lo:hi, lo:hi])).save(out / name)
            writer.writerow([name, row["kx_norm"], row["ky_norm"]])
    _stamp(out, {"from": str(src), "crop_rows_cols": [lo, hi], "frames": len(rows)})
    return table


def rebuild_euv(out: Path) -> Path:
    """Max-normalised EUV frames rescaled to a common mean, centred 256² crop, as one .mat.

    Parameters
    ----------
    out : Path
        Folder to write (created).

    Returns
    -------
    Path
        The ``frames.mat`` the manifest names.
    """
    from PIL import Image
    from scipy.io import savemat

    src = EXTRA / "fpm-euv-sharp-lines81"
    lo, hi = EUV_CROP
    out.mkdir(parents=True, exist_ok=True)
    rows = _read_table(HERE / src.name / "illumination.csv")
    frames = np.stack([np.asarray(Image.open(src / row["path"]), np.float64) for row in rows])
    if frames.shape[1:] != (332, 332):
        raise SystemExit(f"{src}: expected 332² frames, got {frames.shape[1:]}")
    means = frames.mean(axis=(1, 2))
    frames *= (means.mean() / means)[:, None, None]
    stack = np.moveaxis(frames[:, lo:hi, lo:hi], 0, -1).astype(np.float32)   # (H, W, K), as cca reads .mat sources
    savemat(out / "frames.mat", {"frames": stack}, do_compression=True)
    with open(out / "illumination.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["kx_norm", "ky_norm"])
        for row in rows:
            writer.writerow([f"{float(row[key]) * EUV_ILLUMINATION_SCALE:.6f}" for key in ("kx_norm", "ky_norm")])
    _stamp(out, {"from": str(src), "crop_rows_cols": [lo, hi], "frames": len(rows),
                 "illumination_scale": EUV_ILLUMINATION_SCALE,
                 "frame_means_before": [float(m) for m in means]})
    return out / "frames.mat"


def rebuild_janxu(out: Path) -> Path:
    """Centred 128² crop of the student set's 3-exposure amplitudes, as one .mat.

    Parameters
    ----------
    out : Path
        Folder to write (created).

    Returns
    -------
    Path
        The ``frames.mat`` the manifest names.
    """
    from scipy.io import loadmat, savemat

    src = EXTRA / "fpm-janxu-target100"
    lo, hi = JANXU_CROP
    out.mkdir(parents=True, exist_ok=True)
    stack = np.asarray(loadmat(src / "FPM_RawData_3HDR.mat", variable_names=["imlow_HDR"])["imlow_HDR"])
    if stack.shape != (300, 300, 100):
        raise SystemExit(f"{src}: expected imlow_HDR of shape (300, 300, 100), got {stack.shape}")
    savemat(out / "frames.mat", {"imlow_HDR": np.ascontiguousarray(stack[lo:hi, lo:hi]).astype(np.float32)},
            do_compression=True)
    rows = _read_table(HERE / src.name / "illumination.csv")
    with open(out / "illumination.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["kx_norm", "ky_norm"])
        for row in rows:
            writer.writerow([row["kx_norm"], row["ky_norm"]])
    _stamp(out, {"from": str(src / "FPM_RawData_3HDR.mat"), "crop_rows_cols": [lo, hi], "frames": len(rows)})
    return out / "frames.mat"


#: set name → (function, the file its manifest reads, the settings a copy is made with)
CONVERSIONS = {
    "fpm-fdpr-ring93": (rebuild_fdpr, "images.csv", {"crop": FDPR_CROP}),
    "fpm-euv-sharp-lines81": (rebuild_euv, "frames.mat", {"crop": EUV_CROP, "scale": EUV_ILLUMINATION_SCALE}),
    "fpm-janxu-target100": (rebuild_janxu, "frames.mat", {"crop": JANXU_CROP}),
}


def ensure(name: str, *, force: bool = False) -> Path | None:
    """Rebuild one set's converted copy if it is missing or made otherwise (or ``force``); None if none is needed.

    Parameters
    ----------
    name : str
        Corpus set name (its folder in ``benchmarks/corpus``).
    force : bool, optional
        Rebuild even if the copy exists.

    Returns
    -------
    Path or None
        The converted copy's folder.
    """
    if name not in CONVERSIONS:
        return None
    func, marker, settings = CONVERSIONS[name]
    out = OUT / name
    stamp = out / "rebuilt.json"
    made_with = json.loads(stamp.read_text()).get("settings") if stamp.exists() else None
    if force or not (out / marker).exists() or made_with != json.loads(json.dumps(settings)):
        func(out)
        record = json.loads(stamp.read_text())
        _stamp(out, {**record, "settings": settings})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sets", nargs="*", default=list(CONVERSIONS))
    parser.add_argument("--force", action="store_true", help="rebuild copies that exist")
    args = parser.parse_args()
    for name in args.sets:
        if name not in CONVERSIONS:
            raise SystemExit(f"{name}: needs no conversion (sets that do: {', '.join(CONVERSIONS)})")
        print(f"{name}: {ensure(name, force=args.force)}")


if __name__ == "__main__":
    main()
