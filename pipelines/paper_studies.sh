#!/usr/bin/env bash
# The paper's three studies (Holloway et al. 2016, Figs. 6-8) as resumable Dask sweeps.
#
#   pipelines/paper_studies.sh [--workers N | --scheduler tcp://host:8786] [--force]
#
# Each study writes cca-runs/study_<name>/{sweep.csv,sweep.h5,figures/,points/}.
# Re-running skips the points that are already complete; Ctrl-C is safe.
set -euo pipefail
cd "$(dirname "$0")/.."
for study in overlap sar noise; do
    echo "== ${study} study =="
    cca sweep "${study}" "configs/study_${study}.yaml" "$@"
done
