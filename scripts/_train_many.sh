# Sourced by the ablation scripts: the environment for two single-threaded trainings at a
# time, and `train NAME ARGS...`, which trains $OUT/NAME on $DATA with $PRESET (log in
# $OUT/NAME.log) unless it is finished; an interrupted run resumes.
bash scripts/setup_env.sh
PY=.venv/bin/python
export NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
train() {  # name, extra args...
  local name=$1; shift
  [ -f "$OUT/$name/avatar.npz" ] || $PY scripts/train.py --data "$DATA" --out "$OUT/$name" --preset "$PRESET" --resume --no-progress "$@" > "$OUT/$name.log" 2>&1
}
