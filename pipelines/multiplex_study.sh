#!/usr/bin/env bash
# The paper's Fig. 13 study (Section VII): single-shot camera arrays with multiplexed illumination.
# Sweeps N_mux x T on configs/study_multiplex.yaml and writes the table and figures into the study directory.
#   pipelines/multiplex_study.sh                         # N_mux 1,2,3,5,7,10 x T 1,3, 300 iterations
#   pipelines/multiplex_study.sh --n-mux 1,3,7 --patterns 1,3 --out cca-runs/mux-small
set -euo pipefail
cd "$(dirname "$0")/.."
exec python pipelines/multiplex_study.py configs/study_multiplex.yaml "$@"
