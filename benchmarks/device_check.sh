#!/usr/bin/env bash
# Issue 31's GPU checks in one device call (docs/results/planner.md, docs/results/batched-episodes.md):
#   1. the planner's program on both devices (`planner.py --structure-only`: operations, loop iterations,
#      compile and latency of the default planner, the one without gradient steps and the wide ones);
#   2. the whole closed loop on the device (`episodes.py --skip-native --mjx-slots N`) for N random safe
#      boxes with the wide planner (1024 rollouts, no gradient steps), then with the default planner.
# Each part writes its JSON to $OUT as soon as it ends, so a part cut short leaves the others.
#
# On the device machine, from the project root, after `bash ../shared/tools/device-wheels.sh` here
# (run with carry [".whl"]):
#   BOXES=4096 bash benchmarks/device_check.sh
# On this CPU (a dry run of the script itself): BOXES=4 PARTS="structure" bash benchmarks/device_check.sh
set -u
OUT=${OUT:-/tmp/boxjax_device_check}
BOXES=${BOXES:-4096}
PARTS=${PARTS:-"structure wide default"}
mkdir -p "$OUT"
if [ -d .whl ] && ls .whl/*.whl > /dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl \
    || exit 2
  export PYTHONPATH=/tmp/site:$PWD
fi
PY=${PY:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
nvidia-smi --query-gpu=name,memory.total --format=csv > "$OUT/gpu.txt" 2>&1 || true

part() {  # name, time limit (s), command...
  local name=$1 limit=$2
  shift 2
  local t0=$SECONDS
  timeout "$limit" "$@" > "$OUT/$name.json" 2> "$OUT/$name.err"
  echo "$name: exit $? in $((SECONDS - t0)) s" | tee -a "$OUT/parts.txt"
}

for p in $PARTS; do
  case $p in
    structure) part planner_structure 240 "$PY" benchmarks/planner.py --structure-only ;;
    wide) part episodes_wide 300 "$PY" benchmarks/episodes.py --boxes "$BOXES" --skip-native \
            --mjx-slots "$BOXES" --widths --samples 1024 --gradient-steps 0 ;;
    default) part episodes_default 300 "$PY" benchmarks/episodes.py --boxes "$BOXES" --skip-native \
            --mjx-slots "$BOXES" --widths ;;
    *) echo "unknown part $p (structure, wide, default)" >&2; exit 2 ;;
  esac
done
