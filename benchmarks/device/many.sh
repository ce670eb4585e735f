#!/usr/bin/env bash
# Many small trainings at once on the device (run_many.py), across device calls like bg.sh:
#
#   bash benchmarks/device/many.sh start JOBS SLOTS STOP_AFTER WAIT   start run_many.py detached (at most SLOTS at
#                                      once, stopped STOP_AFTER s from now), then wait up to WAIT s for it
#   bash benchmarks/device/many.sh wait WAIT                           wait up to WAIT s more (a later call)
#
# Both pack what the runs logged so far (log.jsonl, config.toml, train_summary.json, each job's output, status.json,
# nvidia-smi samples; no models) into $OUT/many.tgz. Exit 0: all jobs ended; 3: still running (call `wait` within
# 30 s of this call's end, or the machine goes back with them). Env: G (.gpu), OUT, ROOT (/tmp/many), DEVICE_ENV=0.
set -u
cd "$(dirname "$0")/../.."
G=${G:-.gpu}
OUT=${OUT:-/tmp/ctgs_out}
ROOT=${ROOT:-/tmp/many}
source benchmarks/device/lib.sh
mode=${1:?start or wait}
mkdir -p "$OUT"
device_env
if [[ $mode == start ]]; then
  jobs=${2:?jobs file} slots=${3:?slots} stop=${4:?stop after seconds} secs=${5:?seconds to wait}
  rm -rf "$ROOT" && mkdir -p "$ROOT"
  setsid nohup python3 benchmarks/device/run_many.py "$jobs" --slots "$slots" --stop-after "$stop" --root "$ROOT" \
    > "$ROOT/run_many.out" 2>&1 < /dev/null &
  if command -v nvidia-smi > /dev/null; then
    setsid nohup nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used,clocks.sm --format=csv -l 10 \
      > "$ROOT/smi.csv" 2> /dev/null < /dev/null &
  fi
  echo "started run_many.py: $jobs, $slots at once, stop after $stop s"
elif [[ $mode == wait ]]; then
  secs=${2:?seconds to wait}
else
  echo "many.sh: the mode is start or wait, not $mode" >&2; exit 2
fi
t0=$(date +%s)
while [[ ! -f $ROOT/DONE ]] && (( $(date +%s) - t0 < secs )); do sleep 5; done
tar czf "$OUT/many.tgz" -C "$ROOT" --exclude="*.pt" --exclude=checkpoints . 2>/dev/null
python3 - "$ROOT/status.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
from collections import Counter
print(dict(Counter(j["state"] for j in d["jobs"].values())), {k: j.get("wall_s") for k, j in d["jobs"].items() if j.get("wall_s")})
PY
[[ -f $ROOT/DONE ]] && { pkill -f "nvidia-smi --query-gpu=timestamp" 2>/dev/null; exit 0; }
exit 3
