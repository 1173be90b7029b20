#!/usr/bin/env bash
# The paper's tables at the paper's scale on the synthetic head (issue 17):
#   data      make_synthetic.py --preset paper (16 cameras at 550x802, 10 sequences; ~15-20 min)
#   adaptive  the method, preset paper-cpu (depth 4, growth by a budget to 18x the base,
#             6,000 iterations, sampled multi-level supervision)
#   uniform   uniform subdivision to depth 2 (107,254 Gaussians with the coarse levels, the
#             uniform count nearest the adaptive run's ~161k; the report cuts both streams to the
#             smaller count), supervised as the adaptive run
#   finest    finest-level-only supervision (Table 3: 35 %), compared with adaptive; or, with
#             SUPERVISION_ARGS, sup_finest against sup_multi_level: both trained with those
#             options (e.g. the paper's opacity reset and a longer recovery), differing only in
#             the supervision
#   adaptive_seed<k>, uniform_seed<k>   the same two with each seed k of SEEDS (default 1;
#             adaptive vs uniform over seeds, seed 0 being the two runs above)
#   report    scripts/evaluate.py --paper-table (Table 1, Table 3, adaptive vs uniform at matched
#             Gaussian counts, strips, depth colours, time and memory), then docs/BENCHMARKS.md
# Random-order and importance-only (Table 3) are orders of the adaptive run's stream: no training.
#
#   bash scripts/run_paper_table.sh            # a fresh start (refuses if $OUT has runs)
#   bash scripts/run_paper_table.sh --resume   # skip finished runs, continue interrupted ones
#   bash scripts/run_paper_table.sh --resume --report   # the report from the runs finished so far
# Stop it any time (Ctrl-C, session end): checkpoints are atomic and every 500 iterations.
# Environment: DATA (runs/synthetic_paper), OUT (runs/paper), REPORT (runs/report_paper),
#   PRESET (paper-cpu), ITERS (the main runs' iterations; preset's if empty), ABL_ITERS
#   (iterations of finest and the seed runs; preset's if empty: shorter runs are allowed, the
#   report's Training table gives every run's iterations), DATA_ARGS (extra make_synthetic.py
#   options, e.g. "--resolution-scale 0.25 --sequences 3"), EVAL_ARGS (extra evaluate.py
#   options; default "--views 16 --curve-points 12"), UNIFORM_DEPTH (2), ABOUT (text added to the
#   report's description: how the runs were made, when that differs from this script's defaults),
#   SUPERVISION_ARGS (train.py options of the supervision ablation's own pair, e.g.
#   "--opacity-reset-every 1000 --iterations 20000 --grow-stop 0.21"; empty: finest-only is
#   trained like adaptive, with ABL_ITERS, and compared with it), SEEDS (the further seeds of
#   adaptive and uniform, default "1"; e.g. "1 2"),
#   BENCH=0 to skip writing docs/BENCHMARKS.md.
# Time on 2 cores: data ~15-21 min (scripts/bench_data_gen_paper.py); the adaptive run ~1 h
# (0.4 s per iteration at 9k faces, ~0.8 s at 161k: docs/BENCHMARKS.md gives the measured run);
# the report ~10 min. Five full runs do not fit in one 3-hour session: run with --resume across
# sessions, or set ABL_ITERS lower.
set -euo pipefail
cd "$(dirname "$0")/.."
RESUME=0; REPORT_ONLY=0
for a in "$@"; do
  case "$a" in
    --resume) RESUME=1 ;;
    --report) REPORT_ONLY=1 ;;
    *) echo "usage: $0 [--resume] [--report]" >&2; exit 2 ;;
  esac
done
PRESET=${PRESET:-paper-cpu}
DATA=${DATA:-runs/synthetic_paper}
OUT=${OUT:-runs/paper}
REPORT=${REPORT:-runs/report_paper}
ITERS=${ITERS:-}
ABL_ITERS=${ABL_ITERS:-}
DATA_ARGS=${DATA_ARGS:-}
EVAL_ARGS=${EVAL_ARGS:---views 16 --curve-points 12}
PY=${PY:-.venv/bin/python}
[ -x "$PY" ] || { bash scripts/setup_env.sh; PY=.venv/bin/python; }

if [ "$RESUME" = 0 ] && [ "$REPORT_ONLY" = 0 ] && [ -n "$(ls -A "$OUT" 2>/dev/null)" ]; then
  echo "$OUT already holds runs: pass --resume to continue them (or remove $OUT)" >&2; exit 2
fi
mkdir -p "$OUT"
if [ -n "${SUPERVISION_ARGS:-}" ]; then
  # A finished pair from other options would be reported as this one's: refused (--report too).
  was=$(cat "$OUT/supervision_args" 2>/dev/null || true)
  if [ -n "$was" ] && [ "$was" != "$SUPERVISION_ARGS" ]; then
    echo "$OUT/sup_*: trained with SUPERVISION_ARGS=\"$was\", not \"$SUPERVISION_ARGS\": set it back, or remove $OUT/sup_multi_level and $OUT/sup_finest" >&2
    exit 2
  fi
fi
log() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$OUT/progress.log"; }

if [ ! -f "$DATA/transforms_train.json" ]; then
  log "data: $DATA"
  /usr/bin/env time -v $PY scripts/make_synthetic.py --preset paper --out "$DATA" --quiet $DATA_ARGS \
    > "$OUT/data.log" 2>&1 || { cat "$OUT/data.log" >&2; exit 1; }
  tail -n 3 "$OUT/data.log" | head -n 2
fi

train() {  # name, iterations (may be empty), extra args...
  local name=$1 iters=$2; shift 2
  if [ -f "$OUT/$name/avatar.npz" ]; then log "$name: done"; return; fi
  log "$name: training"
  $PY scripts/train.py --data "$DATA" --out "$OUT/$name" --preset "$PRESET" --resume --no-progress \
    ${iters:+--iterations "$iters"} "$@" > "$OUT/$name.log" 2>&1 || { tail -n 20 "$OUT/$name.log" >&2; exit 1; }
  log "$name: $(tail -n 1 "$OUT/$name.log" | cut -c1-200)"
}

UNIFORM="--uniform --max-depth ${UNIFORM_DEPTH:-2} --max-faces 1000000"
if [ "$REPORT_ONLY" = 0 ]; then
  train adaptive "$ITERS"
  # One run (or pair) answers its criterion: before uniform.
  if [ -n "${SUPERVISION_ARGS:-}" ]; then
    echo "$SUPERVISION_ARGS" > "$OUT/supervision_args"
    train sup_multi_level "" $SUPERVISION_ARGS
    train sup_finest "" $SUPERVISION_ARGS --supervision finest
  else
    train finest "$ABL_ITERS" --supervision finest
  fi
  train uniform "$ITERS" $UNIFORM
  for s in ${SEEDS:-1}; do
    train "adaptive_seed$s" "$ABL_ITERS" --seed "$s"
    train "uniform_seed$s" "$ABL_ITERS" --seed "$s" $UNIFORM
  done
fi

[ -f "$OUT/adaptive/avatar.npz" ] || { echo "no finished adaptive run in $OUT: nothing to report" >&2; exit 1; }
args=()
if [ -n "${SUPERVISION_ARGS:-}" ]; then
  [ -f "$OUT/sup_finest/avatar.npz" ] && [ -f "$OUT/sup_multi_level/avatar.npz" ] &&
    args+=(--finest-only "$OUT/sup_finest" --multi-level "$OUT/sup_multi_level")
else
  [ -f "$OUT/finest/avatar.npz" ] && args+=(--finest-only "$OUT/finest")
fi
[ -f "$OUT/uniform/avatar.npz" ] && args+=(--uniform "uniform=$OUT/uniform" --compare "uniform=$OUT/uniform")
for s in ${SEEDS:-1}; do
  [ -f "$OUT/adaptive_seed$s/avatar.npz" ] && args+=(--adaptive "adaptive_seed$s=$OUT/adaptive_seed$s")
  [ -f "$OUT/uniform_seed$s/avatar.npz" ] && args+=(--uniform "uniform_seed$s=$OUT/uniform_seed$s")
done
log "report: $REPORT"
$PY scripts/evaluate.py --run "$OUT/adaptive" --out "$REPORT" --no-progress --paper-table "${args[@]}" $EVAL_ARGS \
  --about "The paper-scale synthetic head (scripts/run_paper_table.sh): adaptive multi-level training (preset $PRESET) against uniform subdivision to depth ${UNIFORM_DEPTH:-2} and finest-level-only supervision.${ABOUT:+ $ABOUT}" \
  > "$OUT/report.log" 2>&1 || { tail -n 30 "$OUT/report.log" >&2; exit 1; }
if [ "${BENCH:-1}" = 1 ]; then
  # bench.py keeps the page's other sections as they are and adds or replaces this report's.
  $PY scripts/bench.py --only none --report "$REPORT" >> "$OUT/report.log" 2>&1
fi
log "report: $REPORT/paper_table.md"
