# Sourced by the issue-16 studies (run_prefix_study.sh, run_backdrop_study.sh) after they set
# OUT: the environment, both synthetic heads, and the run helpers they share.
# They train train.py's default (cpu) preset, which the sections they write say: a PRESET asked
# for (a smoke run) is refused, not ignored for hours of runs that then rewrite docs/.
if [ "${PRESET:-cpu}" != cpu ]; then
  echo "$0: no PRESET here (the cpu preset only); BENCHMARKS=FILE and REPORTS=DIR write elsewhere than docs/" >&2
  exit 2
fi
bash scripts/setup_env.sh
PY=.venv/bin/python
DATA=${DATA:-runs/synthetic}
DATA_COARSE=${DATA_COARSE:-runs/synth_coarse}
BENCHMARKS=${BENCHMARKS:-docs/BENCHMARKS.md}
REPORTS=${REPORTS:-docs}
mkdir -p "$OUT/default" "$OUT/coarse"
[ -f "$DATA/transforms_train.json" ] || $PY scripts/make_synthetic.py --out "$DATA" --quiet
[ -f "$DATA_COARSE/transforms_train.json" ] ||
  $PY scripts/make_synthetic.py --out "$DATA_COARSE" --template-subdivisions 3 --quiet

train() {  # data, run folder, extra args...
  local data=$1 run=$2; shift 2
  [ -f "$run/avatar.npz" ] ||
    $PY scripts/train.py --data "$data" --out "$run" --resume --no-progress "$@" >> "$run.log" 2>&1 ||
    { echo "$run: training ended with exit $?, $run.log ends:" >&2; tail -n 5 "$run.log" >&2; return 1; }
}
name() {  # base name, seed: NAME for seed 0, NAME_seed<k> otherwise (evaluate.py's grouping)
  if [ "$2" = 0 ]; then echo "$1"; else echo "$1_seed$2"; fi
}
seed_args() {  # folder, main name, names...: --compare every seed of each name but the main run (seed 0),
  # --budget-compare the main name's other seeds (evaluate.py groups NAME_seed<k> with NAME)
  local dir=$1 main=$2; shift 2
  for n in "$@"; do
    for s in $SEEDS; do
      local r; r=$(name "$n" "$s")
      [ "$r" = "$main" ] || echo --compare "$r=$dir/$r"
      if [ "$n" = "$main" ] && [ "$s" != 0 ]; then echo --budget-compare "$r=$dir/$r"; fi
    done
  done
}
