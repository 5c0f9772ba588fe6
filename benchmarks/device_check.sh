#!/usr/bin/env bash
# Issue 31's GPU checks, prepared for a device call (docs/results/planner.md, docs/results/batched-episodes.md):
#   planner      the planner's program on the accelerator (`planner.py --structure-only --structure-devices
#                accelerator`: operations, loop iterations, compile and the median call of the default
#                planner, the one without gradient steps and the wide one, one box and 16 vmapped): the
#                <= 20 ms target;
#   wide         the whole closed loop on the device (`episodes.py --skip-native --mjx-slots N`) for N
#                random safe boxes with the wide planner (1024 rollouts, no gradient steps): the >= 50
#                episodes/s at 4096 boxes target;
#   default      the same with the default planner;
#   planner_cpu  the planner part on the same machine's CPU (the ratio of the two devices).
# Each part writes its JSON to $OUT as soon as it ends, so a part cut short leaves the others, and its
# stderr (the planner's per-device results, the loop's episodes ended so far) says how far it got.
#
# On the device machine, from the project root, after `bash ../shared/tools/device-wheels.sh` here
# (run with carry [".whl"]), in two calls of under 10 minutes:
#   BOXES=4096 bash benchmarks/device_check.sh                          # planner, wide (8.5 min at most)
#   BOXES=4096 PARTS="default planner_cpu" bash benchmarks/device_check.sh
# On this CPU (a dry run of the script itself): BOXES=4 PARTS="planner_cpu wide" bash benchmarks/device_check.sh
set -u
OUT=${OUT:-/tmp/boxjax_device_check}
BOXES=${BOXES:-4096}
PARTS=${PARTS:-"planner wide"}
for p in $PARTS; do  # every part named checked before any work
  case $p in planner | planner_cpu | wide | default) ;;
    *) echo "unknown part $p (planner, wide, default, planner_cpu)" >&2; exit 2 ;;
  esac
done
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

STRUCTURE=(benchmarks/planner.py --structure-only --unrolled-only
           --structure-planners default no_gradient wide1024_no_gradient)
for p in $PARTS; do
  case $p in
    planner) part planner_structure 200 "$PY" "${STRUCTURE[@]}" --structure-devices accelerator ;;
    planner_cpu) part planner_structure_cpu 240 "$PY" "${STRUCTURE[@]}" --structure-devices cpu ;;
    wide) part episodes_wide 300 "$PY" benchmarks/episodes.py --boxes "$BOXES" --skip-native \
            --mjx-slots "$BOXES" --widths --samples 1024 --gradient-steps 0 ;;
    default) part episodes_default 300 "$PY" benchmarks/episodes.py --boxes "$BOXES" --skip-native \
            --mjx-slots "$BOXES" --widths ;;
  esac
done
