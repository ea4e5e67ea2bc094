"""Copy the corpus sets' upstream files from clones of their source repositories.

Six of the corpus's eight sets are not in ``../shared/datasets``; their files are
copied unchanged, at a fixed commit, into ``../corpus_extra/<set>/`` beside the
checkout (never into the repository: several sets carry no licence). Their
illumination tables, derived from the upstream code, are kept in the repository
beside each manifest (``benchmarks/corpus/<set>/illumination.csv``).

Usage::

    git clone https://github.com/ArianaGu/EUV_FPM clones/EUV_FPM      # … one clone per repository
    python benchmarks/corpus/collect.py --clones clones [SET ...]      # default: every set below

A clone may be a work tree or a bare mirror; ``--clones`` is searched for
``<name>``, ``<owner>+<name>`` and ``<owner>/<name>``. Files that are there and
identical are left alone; a file that differs is an error (nothing here
overwrites what it did not write).
"""

from __future__ import annotations

import argparse
import fnmatch
import subprocess
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
EXTRA = ROOT.parent / "corpus_extra"
if not EXTRA.is_dir() and Path("/work/corpus_extra").is_dir():  # a worktree elsewhere than beside it
    EXTRA = Path("/work/corpus_extra")

#: set → (repository, commit, [(upstream path or glob, destination folder inside the set's folder)])
SOURCES = {
    "fpm-zuo-usaf11": ("MLWise112358/DFNN_for_FPM_reconstruction", "304d11d54cb717d5ddaf13c57532ffb885230137",
                       [("data/test_11x11_USAF/test (*).tif", "frames")]),
    "fpm-pbnn-bloodcell13": ("zhangjizhou-bit/PbNN-CA", "eac9a1a0e2c10dfb4a25ef041497eea258349fc9",
                             [("mat_data_add/new_cell_120.mat", "."), ("LICENSE.txt", ".")]),
    "fpm-euv-sharp-lines81": ("ArianaGu/EUV_FPM", "2c06e7792f661b7f6b133024736058927cfe84e7",
                              [("real_data/fp_data/defect_5um_sx*_sy*.png", "fp_data")]),
    "fpm-janxu-target100": ("janxu2417/FPM-Experiment", "c58a39dc1c34d45f3d7ac95a1a437797b270bd84",
                            [("Code/FPM_RawData_3HDR.mat", "."), ("Code/FPM_RawData.mat", ".")]),
    "fpm-fdpr-ring93": ("THUHoloLab/feature-domain-phase-retrieval", "7ed5f884f4e414ab2e1a264ec0239123a88ce75a",
                        [("Demo/Fourier ptychography/dataset/225.000_*.TIF", "dataset"),
                         ("Demo/Fourier ptychography/loc_pos.mat", "."), ("LICENSE", ".")]),
    "fpm-elfpie-usaf64": ("ShuheZhang-MUMC/elfpie_algorithm", "9ba2c628b16a5bf09bb5436f622ca2ddc800d2f6",
                          [("usaf_demo/raw_image20180708/pross/*.tif", "pross")]),
}


def find_clone(clones: Path, repository: str) -> Path:
    """The clone of ``owner/name`` under ``clones``, as ``name``, ``owner+name`` or ``owner/name``."""
    owner, name = repository.split("/")
    for candidate in (clones / name, clones / f"{owner}+{name}", clones / owner / name):
        if candidate.is_dir():
            return candidate
    raise SystemExit(f"{clones}: no clone of {repository} (expected {clones / name}); "
                     f"git clone https://github.com/{repository} {clones / name}")


def _git(clone: Path, *args: str) -> bytes:
    result = subprocess.run(["git", "-C", str(clone), *args], capture_output=True)
    if result.returncode != 0:
        raise SystemExit(f"{clone}: git {' '.join(args)} failed: {result.stderr.decode().strip()}")
    return result.stdout


def collect(name: str, clones: Path) -> int:
    """Copy one set's files from its clone at the pinned commit; returns how many were written."""
    repository, commit, patterns = SOURCES[name]
    clone = find_clone(clones, repository)
    listing = _git(clone, "ls-tree", "-r", "--name-only", commit).decode().splitlines()
    written = 0
    for pattern, folder in patterns:
        matches = [path for path in listing if fnmatch.fnmatchcase(path, pattern)]
        if not matches:
            raise SystemExit(f"{repository}@{commit[:8]}: nothing matches {pattern!r}")
        destination = EXTRA / name / folder
        destination.mkdir(parents=True, exist_ok=True)
        for path in matches:
            data = _git(clone, "show", f"{commit}:{path}")
            if data.startswith(b"version https://git-lfs"):
                raise SystemExit(f"{repository}@{commit[:8]}:{path} is a Git LFS pointer: "
                                 f"run `git lfs pull` in {clone}")
            target = destination / Path(path).name
            if target.exists():
                if target.read_bytes() != data:
                    raise SystemExit(f"{target}: exists and differs from {repository}@{commit[:8]}:{path}; "
                                     "move it away first")
                continue
            partial = target.with_name(target.name + ".part")
            partial.write_bytes(data)
            partial.rename(target)
            written += 1
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sets", nargs="*", default=list(SOURCES))
    parser.add_argument("--clones", type=Path, required=True, help="folder holding the repositories' clones")
    args = parser.parse_args()
    for name in args.sets:
        if name not in SOURCES:
            raise SystemExit(f"{name}: not a set this script collects ({', '.join(SOURCES)})")
        print(f"{name}: {collect(name, args.clones)} files written to {EXTRA / name}")


if __name__ == "__main__":
    main()
