#!/usr/bin/env bash
# The paper's Fig. 13 study (Section VII): single-shot camera arrays with multiplexed illumination.
# Sweeps N_mux x T on configs/study_multiplex.yaml as a resumable Dask sweep: the table
# (sweep.csv, sweep.h5), RMSE and MTF20 vs N_mux per T, a montage of recoveries, and each
# point's coverage map (points/*/report/coverage.png).
#   pipelines/multiplex_study.sh                       # N_mux 1,2,3,5,7,10 x T 1,3
#   pipelines/multiplex_study.sh --workers 1 --out-dir cca-runs/mux
# python pipelines/multiplex_study.py draws the same study with a coverage montage, one point at a time.
set -euo pipefail
cd "$(dirname "$0")/.."
exec cca sweep grid configs/study_multiplex.yaml \
    --set multiplex.n_mux=1,2,3,5,7,10 --set multiplex.patterns=1,3 "$@"
