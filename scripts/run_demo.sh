#!/usr/bin/env bash
# The main job on the embedded default: synthetic head -> trained avatar -> stream -> report.
# Creates the project's virtual environment on first use. Outputs go to runs/ (git-ignored).
#   PRESET=tiny bash scripts/run_demo.sh   # a smoke run instead of the cpu preset's few minutes
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
PY=.venv/bin/python
PRESET=${PRESET:-cpu}
DATA=${DATA:-runs/synthetic}
RUN=${RUN:-runs/avatar_$PRESET}
REPORT=${REPORT:-runs/report_$PRESET}
if [ ! -f "$DATA/transforms_train.json" ]; then
  $PY scripts/make_synthetic.py --out "$DATA"
fi
if [ ! -f "$RUN/avatar.npz" ]; then
  $PY scripts/train.py --data "$DATA" --out "$RUN" --preset "$PRESET" --resume
fi
$PY scripts/export.py --run "$RUN" --stream "$RUN/avatar.pavs" --ply "$RUN/frame0_25pct.ply" --budget 25 --frame 0
$PY scripts/evaluate.py --run "$RUN" --out "$REPORT"
echo "report: $REPORT/report.md"
