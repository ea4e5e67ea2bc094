"""Where, by illumination angle, cca's and a peer's objects fit a corpus set differently (the common reading).

Reads cca's default result and one peer setting's saved run from a corpus run's working folder
(``python benchmarks/real_corpus.py`` first), reads both the common way
(:func:`real_model.common_reading`) and splits the squared misfit over the frames by how far each
capture's pupil centre lies from the spectrum's origin, in pupil radii (below 1: bright field). Each
share is of the whole set's squared measured amplitude, so a row's two shares differ by what that
ring of captures adds to the difference of the two residuals over all frames squared.

Usage::

    python benchmarks/residual_by_angle.py fpm-usaf-aidukas32
    python benchmarks/residual_by_angle.py fpm-zuo-usaf11 --peer "PtyLab mPIE + pupil βP 0.25" --iteration 89
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import real_corpus as corpus  # noqa: E402
from real_methods import read_cca_recovery, run_peer  # noqa: E402
from real_model import common_reading  # noqa: E402

#: Ring edges in pupil radii.
RINGS = (0.0, 0.9, 1.1, 1.5, 2.0, 3.0, 5.0, np.inf)


def peer_snapshot(label: str, data, workdir: Path, iteration: int | None):
    """The saved snapshot of a peer setting (its last, or the one of ``iteration``) and its iteration."""
    family, method, options = corpus.PEERS[label]
    iterations = 100
    key = json.dumps({"data": corpus.data_digest(data), "method": method, "options": options,
                      "iterations": iterations}, sort_keys=True)
    res = run_peer(method, dict(options, label=f"{options['label']}{iterations}"), iterations, data, workdir, 3600,
                   reuse=True, input_key=hashlib.sha1(key.encode()).hexdigest())
    if res["status"] != "ok":
        raise SystemExit(f"{label}: no saved run in {workdir} ({res.get('status')}); run benchmarks/real_corpus.py")
    snaps = res["snaps"]
    pick = len(snaps) - 1 if iteration is None else next(
        (i for i, (it, _, _) in enumerate(snaps) if it == iteration), None)
    if pick is None:
        raise SystemExit(f"{label}: no snapshot at iteration {iteration} (have {[it for it, _, _ in snaps]})")
    return snaps[pick][2], snaps[pick][0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("set", help="corpus set name, e.g. fpm-usaf-aidukas32")
    parser.add_argument("--peer", default="PtyLab mPIE + pupil βP 0.05", help="peer setting (real_corpus.PEERS)")
    parser.add_argument("--iteration", type=int, default=None, help="the peer's snapshot (default its last)")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "corpus", help="the corpus run's folder")
    args = parser.parse_args()

    workdir = args.out / "work" / args.set
    data, frames, factor = corpus.load_set(corpus.CorpusSet(args.set), workdir, reuse=True)
    cca, _ = read_cca_recovery(workdir / "cca_defaults.h5", data)
    peer, iteration = peer_snapshot(args.peer, data, workdir, args.iteration)
    readings = {"cca": common_reading(cca, frames, factor), f"{args.peer} (it {iteration})": common_reading(
        peer, frames, factor)}
    radius = np.hypot(*np.asarray(frames.centres, np.float64).T) / frames.radius
    total = next(iter(readings.values())).reference2.sum()
    print(f"{args.set}: residual all / BF / DF")
    for name, reading in readings.items():
        r = reading.residual
        print(f"  {name:40s} {r['all']:.4f} / {r['bright_field']:.4f} / {r['dark_field']:.4f}")
    names = list(readings)
    print(f"\n{'ring (pupil radii)':>18} {'captures':>8} {'light':>7}  " + "  ".join(f"{n[:22]:>22}" for n in names)
          + "   difference")
    for low, high in zip(RINGS[:-1], RINGS[1:]):
        ring = (radius >= low) & (radius < high)
        if not ring.any():
            continue
        shares = [readings[n].error2[ring].sum() / total for n in names]
        print(f"{low:8.1f} – {high:<7.1f} {int(ring.sum()):8d} {readings[names[0]].reference2[ring].sum() / total:7.4f}  "
              + "  ".join(f"{v:22.5f}" for v in shares) + f"   {shares[0] - shares[1]:+.5f}")


if __name__ == "__main__":
    main()
