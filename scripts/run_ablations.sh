#!/usr/bin/env bash
# The paper's training ablations on the synthetic default, then one report comparing them
# with the adaptive multi-level run of scripts/run_demo.sh:
#   uniform subdivision to depth 2 and 3 (all levels supervised, and depth 2 with sampled
#   levels), finest-level-only and sampled-level supervision, the default with another seed
#   (how far two runs of the same method land apart), and both supervisions with a doubled
#   growth threshold (fewer Gaussians).
# Runs two trainings at a time, single-threaded each (2 cores): about 1.5 h on 2 cores.
# Outputs: the main run runs/avatar_$PRESET (run_demo.sh's), the ablations under
# runs/ablations_$PRESET, the report runs/report_$PRESET; a finished run is skipped, an
# interrupted one resumes. PRESET=tiny makes a smoke run of the whole script (a few minutes).
set -euo pipefail
cd "$(dirname "$0")/.."
PRESET=${PRESET:-cpu}
DATA=${DATA:-runs/synthetic}
MAIN=${MAIN:-runs/avatar_$PRESET}
# One folder per preset: a finished run is skipped whatever preset trained it, and a smoke run
# with PRESET=tiny must not stand in for the cpu preset's ablations afterwards.
OUT=runs/ablations_$PRESET
source scripts/_train_many.sh
[ -f "$DATA/transforms_train.json" ] || $PY scripts/make_synthetic.py --out "$DATA"
mkdir -p "$OUT"
(OUT=runs; train "avatar_$PRESET") & train uniform_d2 --uniform --max-depth 2 --max-faces 1000000 & wait_all
train finest_only --supervision finest & train sampled --supervision sampled & wait_all
train uniform_d3 --uniform --max-depth 3 --max-faces 1000000 & train seed1 --seed 1 & wait_all
train uniform_d2_sampled --uniform --max-depth 2 --max-faces 1000000 --supervision sampled & \
  train all_eps4e-4 --grad-threshold 4e-4 & wait_all
train sampled_eps4e-4 --supervision sampled --grad-threshold 4e-4
$PY scripts/evaluate.py --run "$MAIN" --out "runs/report_$PRESET" --no-progress \
  --compare adaptive_seed1="$OUT/seed1" --name adaptive \
  --compare uniform_d2="$OUT/uniform_d2" --compare uniform_d3="$OUT/uniform_d3" \
  --compare uniform_d2_sampled="$OUT/uniform_d2_sampled" \
  --compare finest_only="$OUT/finest_only" --compare sampled="$OUT/sampled" \
  --compare all_eps4e-4="$OUT/all_eps4e-4" --compare sampled_eps4e-4="$OUT/sampled_eps4e-4"
# The report rewrote MAIN/avatar.pavs without the template; run_demo.sh leaves it self-contained.
$PY scripts/export.py --run "$MAIN" --stream "$MAIN/avatar.pavs"
echo "report: runs/report_$PRESET/report.md"
