#!/usr/bin/env bash
# The paper's Fig. 5 case, one stage at a time (what `cca run configs/headline.yaml` does in one go).
# Usage: pipelines/headline.sh [OUT_DIR]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
out="${1:-cca-runs/headline-stages}"
mkdir -p "$out"
cca simulate "$here/configs/headline.yaml" -o "$out/captures.h5" --force
cca reconstruct "$out/captures.h5" -o "$out/recon.h5" --config "$here/configs/headline.yaml" --force
cca report "$out/recon.h5" -o "$out/report" --force
cca info "$out/recon.h5"
