#!/usr/bin/env bash
# Issue 16's measurements: every prefix a whole head, with and without the coarse levels, on
# the default synthetic head (5,120-face template) and on the same head tracked by a coarser
# 1,280-face template (make_synthetic.py --template-subdivisions 3), six seeds each, because
# the coarse levels' cost at 100 % moves by 0.1-0.2 dB from seed to seed. On the coarse-template
# head also a finest-level tail (--finest-tail 0.25) with and without coarse levels (coarse
# weight 0.75 with them). Then evaluate.py writes the two BENCHMARKS.md sections
# "Every prefix a whole head: ... (issue 16)" and their reports under docs/. Cumulative coarse
# levels (--coarse-mode cumulative), as those sections were measured: the default is backdrop
# stand-ins since 2026-11-28, which scripts/run_backdrop_study.sh measures.
#
# The runs train one after another with the default threads (2 on the project's VM), as the
# committed sections were measured: about 2.5 min per run there, 36 runs, 1.5 h plus 15 min
# of evaluation. Outputs under runs/prefix16/; a finished run is skipped, an interrupted one
# resumes. BENCHMARKS=... writes the sections into another Markdown file (default
# docs/BENCHMARKS.md); REPORTS=DIR writes the reports there instead of docs/.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=runs/prefix16
# shellcheck source=scripts/_two_heads.sh
source scripts/_two_heads.sh
SEEDS="0 1 2 3 4 5"
for s in $SEEDS; do
  train "$DATA" "$OUT/default/$(name default $s)" --seed "$s" --coarse-mode cumulative
  train "$DATA" "$OUT/default/$(name no_coarse $s)" --seed "$s" --no-coarse
  train "$DATA_COARSE" "$OUT/coarse/$(name default $s)" --seed "$s" --coarse-mode cumulative
  train "$DATA_COARSE" "$OUT/coarse/$(name no_coarse $s)" --seed "$s" --no-coarse
  train "$DATA_COARSE" "$OUT/coarse/$(name tail_cw075 $s)" --seed "$s" --coarse-weight 0.75 --finest-tail 0.25 --coarse-mode cumulative
  train "$DATA_COARSE" "$OUT/coarse/$(name no_coarse_tail $s)" --seed "$s" --no-coarse --finest-tail 0.25
done

SHARED="stream version 5 without the embedded template (the receiver has the tracked mesh): after the coarse levels, any face as soon as its parent has arrived, by importance measured on the levels up to its own, each pixel weighted by the error of the levels below (the ablation line \"every root first\" scores version 4's level-by-level order on the same faces). The seed tables give mean ± sd at 100 % and the per-seed differences (the coarse levels' cost per seed is default minus no_coarse); the criteria list scores seed 0, then every seed (scripts/run_prefix_study.sh)."

# shellcheck disable=SC2046  # seed_args' words are meant to split
$PY scripts/evaluate.py --run "$OUT/default/default" --name default --data "$DATA" --out "$REPORTS/report_prefix" \
  --no-coarse-run "$OUT/default/no_coarse" --views 16 --curve-views 8 \
  $(seed_args "$OUT/default" default default no_coarse) --budget-compare no_coarse="$OUT/default/no_coarse" \
  --benchmarks "$BENCHMARKS" --section 'Every prefix a whole head: default synthetic head (issue 16)' --no-progress \
  --about "Default synthetic head (5,120-face template), the cpu preset (4,000 iterations) with cumulative coarse levels (1/32 and 1/16 of the template's faces, loss weight 0.5) against the same training without them (--no-coarse), six seeds each (0-5; this run is seed 0); $SHARED"

# shellcheck disable=SC2046
$PY scripts/evaluate.py --run "$OUT/coarse/default" --name default --data "$DATA_COARSE" --out "$REPORTS/report_prefix_coarse" \
  --no-coarse-run "$OUT/coarse/no_coarse" --views 16 --curve-views 8 \
  $(seed_args "$OUT/coarse" default default no_coarse tail_cw075 no_coarse_tail) \
  --budget-compare tail_cw075="$OUT/coarse/tail_cw075" --budget-compare no_coarse="$OUT/coarse/no_coarse" \
  --benchmarks "$BENCHMARKS" --section 'Every prefix a whole head: coarse-template head (issue 16)' --no-progress \
  --about "The synthetic head tracked by a coarser 1,280-face template (make_synthetic.py --template-subdivisions 3), the cpu preset (4,000 iterations) with cumulative coarse levels (1/32 and 1/16 of the template's faces, loss weight 0.5) against the same training without them (--no-coarse), six seeds each (0-5; this run is seed 0). Also six seeds each of the coarse levels at loss weight 0.75 with a finest-level tail (--coarse-weight 0.75 --finest-tail 0.25: the last quarter supervises the finest image alone, coarse and template Gaussians frozen) and of its proper comparator, the same tail without coarse levels (--no-coarse --finest-tail 0.25), to see whether the tail pays for the coarse levels; $SHARED"
echo "sections written to $BENCHMARKS; reports: $REPORTS/report_prefix, $REPORTS/report_prefix_coarse"
