#!/usr/bin/env bash
# Adaptive against uniform subdivision with twice the image resolution: the coarse-template
# synthetic head of scripts/run_coarse_ablation.sh (1280-face tracked template, images ray-cast
# from the 5120-face surface) rendered at 176x256 px instead of 88x128, so that finer levels have
# pixels to explain. Coarser levels weighted 0.3 (the finest 1) in every run: adaptive (seeds 0
# and 1) and uniform subdivision to depth 2 and 3; then one report. Two trainings at a time,
# single-threaded each: about 1 h on 2 cores.
# Outputs under runs/coarse256/; a finished run is skipped, an interrupted one resumes.
set -euo pipefail
cd "$(dirname "$0")/.."
# The report's text and the level weights below are the cpu preset's: another PRESET (a smoke
# run) is refused, not ignored for hours.
[ "${PRESET:-cpu}" = cpu ] || { echo "$0: no PRESET here (the cpu preset only)" >&2; exit 2; }
PRESET=cpu
DATA=${DATA:-runs/synthetic_coarse256}
OUT=runs/coarse256
source scripts/_train_many.sh
[ -f "$DATA/transforms_train.json" ] ||
  $PY scripts/make_synthetic.py --out "$DATA" --template-subdivisions 3 --resolution 256 --quiet
mkdir -p "$OUT"
# --level-weights counts levels from the coarsest: the cpu preset's two coarse levels (whose
# weights --coarse-weight 0.5 also scales), the template, then depth 1-3.
W="--level-weights 0.3,0.3,0.3,0.3,0.3,1"
train adaptive_w0.3 $W & train uniform_d3_w0.3 --uniform --max-depth 3 --max-faces 1000000 $W & wait_all
train uniform_d2_w0.3 --uniform --max-depth 2 --max-faces 1000000 --level-weights 0.3,0.3,0.3,0.3,1 & \
  train adaptive_w0.3_seed1 --seed 1 $W & wait_all
$PY scripts/evaluate.py --run "$OUT/adaptive_w0.3" --out runs/report_coarse256 --no-progress \
  --compare adaptive_w0.3_seed1="$OUT/adaptive_w0.3_seed1" \
  --compare uniform_d2_w0.3="$OUT/uniform_d2_w0.3" --compare uniform_d3_w0.3="$OUT/uniform_d3_w0.3" \
  --name adaptive_w0.3 \
  --about "The coarse-template synthetic head (1280-face tracked template, images ray-cast from the 5120-face surface) at 176x256 px, twice the resolution of docs/report_coarse. Every level but the finest weighted 0.3 in every run (the coarse levels also times the coarse weight 0.5). Adaptive subdivision (this run, and seed 1) against uniform subdivision to depth 2 and 3 (scripts/run_detail_ablation.sh)."
echo "report: runs/report_coarse256/report.md"
