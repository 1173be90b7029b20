#!/usr/bin/env bash
# The main job on the embedded default: synthetic head -> trained avatar -> stream -> report.
# Creates the project's virtual environment on first use. Outputs go to runs/ (git-ignored).
#   PRESET=tiny bash scripts/run_demo.sh   # a smoke run instead of the cpu preset's ~10 minutes
# DATA, RUN and REPORT may name other folders; relative ones are taken from where you run it.
set -euo pipefail
here=$(pwd)
abs() { case "$1" in /*) printf '%s' "$1" ;; *) printf '%s/%s' "$here" "$1" ;; esac; }
[ -n "${DATA:-}" ] && DATA=$(abs "$DATA")
[ -n "${RUN:-}" ] && RUN=$(abs "$RUN")
[ -n "${REPORT:-}" ] && REPORT=$(abs "$REPORT")
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
if [ -f "$RUN/config.json" ]; then  # a finished or interrupted run is reused only on the same data
  $PY - "$RUN" "$DATA" <<'PYEOF'
import json, os, sys
run, data = sys.argv[1:]
try:
    was = json.load(open(os.path.join(run, "config.json"), encoding="utf-8")).get("data")
except (OSError, ValueError, AttributeError):
    was = None
if was and os.path.realpath(was) != os.path.realpath(data):
    sys.exit(f"error: {run} was trained on {was}, not {os.path.abspath(data)}: set RUN to another folder, or remove it")
PYEOF
fi
if [ ! -f "$RUN/avatar.npz" ]; then
  $PY scripts/train.py --data "$DATA" --out "$RUN" --preset "$PRESET" --resume
fi
# The report rewrites RUN/avatar.pavs without the template (its budgets count what a receiver that
# has the mesh is sent); exporting after it leaves the run the self-contained stream.
$PY scripts/evaluate.py --run "$RUN" --out "$REPORT"
$PY scripts/export.py --run "$RUN" --stream "$RUN/avatar.pavs" --ply "$RUN/frame0_25pct.ply" --budget 25 --frame 0
echo "report: $(cd "$REPORT" && pwd)/report.md"
