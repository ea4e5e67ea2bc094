"""The positions' orientation trial on the recorded corpus: as given (nothing should be warned of) and swapped.

For every set a corpus run ingested (``benchmarks/results/corpus/work/<set>/raw.h5``: run
``python benchmarks/real_corpus.py --tools cca`` first), runs
:func:`cca_cli.library.orientation.orientation_trial` on the captures as ingested and on the same captures
with their positions' x and y swapped, and prints each arrangement's residual, the arrangement the trial would
warn of, the ratio that decides it (best other arrangement over the given one: a warning below
``CLEARLY_BETTER``) and the time.

Usage::

    python benchmarks/orientation_trial.py
    python benchmarks/orientation_trial.py --sets fpm-zuo-usaf11,fpm-janxu-target100 --passes 16
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cca_cli as cca
from cca_cli.library.orientation import ARRANGEMENTS, CLEARLY_BETTER, arranged, orientation_trial
from cca_cli.library.recovery import without_dead_captures

HERE = Path(__file__).resolve().parent
SHORT = {"as given": "given", "x and y swapped": "swapped", "x flipped": "flipped",
         "x and y swapped, then x flipped": "swapped+flipped"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=HERE / "results" / "corpus" / "work",
                        help="a corpus run's working folder")
    parser.add_argument("--sets", default="", help="comma list of set names (default: every one ingested)")
    parser.add_argument("--passes", type=int, default=None, help="passes of each trial (default: the library's)")
    args = parser.parse_args()

    wanted = [s for s in args.sets.split(",") if s]
    paths = sorted(p for p in args.work.glob("*/raw.h5") if not wanted or p.parent.name in wanted)
    if not paths:
        raise SystemExit(f"no raw.h5 under {args.work}; run benchmarks/real_corpus.py --tools cca first")
    options = {} if args.passes is None else {"passes": args.passes}
    print(f"{'set':24} {'positions':9} " + " ".join(f"{SHORT[n]:>15}" for n in ARRANGEMENTS)
          + f" {'warns of':>16} {'ratio':>6} {'s':>5}")
    for path in paths:
        captures = without_dead_captures(cca.load(path))
        for label, given in (("as given", captures), ("swapped", arranged(captures, "x and y swapped"))):
            start = time.perf_counter()
            trial = orientation_trial(given, **options)
            seconds = time.perf_counter() - start
            others = min(v for k, v in trial.residuals.items() if k != "as given")
            ratio = others / trial.residuals["as given"]
            warned = SHORT[trial.clearly_other] if trial.clearly_other else "—"
            print(f"{path.parent.name:24} {label:9} " + " ".join(f"{trial.residuals[n]:>15.4f}" for n in ARRANGEMENTS)
                  + f" {warned:>16} {ratio:>6.3f} {seconds:>5.2f}", flush=True)
    print(f"a warning names an arrangement whose residual is under {CLEARLY_BETTER} times the given one's")


if __name__ == "__main__":
    main()
