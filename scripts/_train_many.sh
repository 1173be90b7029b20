# Sourced by the ablation scripts: the environment for two single-threaded trainings at a
# time, `train NAME ARGS...`, which trains $OUT/NAME on $DATA with $PRESET (log in
# $OUT/NAME.log, appended: a resumed run's keeps the interrupted part) unless it is finished
# (an interrupted run resumes), and `wait_all`, which
# waits for the trainings started with & and fails if one of them did.
bash scripts/setup_env.sh
PY=.venv/bin/python
export NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
train() {  # name, extra args...
  local name=$1; shift
  [ -f "$OUT/$name/avatar.npz" ] ||
    $PY scripts/train.py --data "$DATA" --out "$OUT/$name" --preset "$PRESET" --resume --no-progress "$@" >> "$OUT/$name.log" 2>&1 ||
    { echo "$OUT/$name: training ended with exit $?, $OUT/$name.log ends:" >&2; tail -n 5 "$OUT/$name.log" >&2; return 1; }
}
wait_all() {  # a bare `wait` returns 0 even when a training failed: the study would go on without it
  local pid rc=0
  for pid in $(jobs -p); do wait "$pid" || rc=1; done
  return "$rc"
}
