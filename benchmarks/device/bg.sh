#!/usr/bin/env bash
# A training longer than one device call (10 minutes): it runs in its own process session, which outlives the call
# while the machine stays warm (30 s after a call ends), and the next call waits for it again.
#
#   bash benchmarks/device/bg.sh start NAME SECS TRAIN_ARGS...   start `ctgs train TRAIN_ARGS -o /tmp/runs/NAME -q`
#                                                                 detached, then wait up to SECS for it
#   bash benchmarks/device/bg.sh wait NAME SECS                   wait up to SECS more (a later call)
#
# Exit 0: the run finished, and was exported, compressed and evaluated (records in $OUT/pipe_NAME, with
# $OUT/bg_NAME.log); 3: still running (call `wait` again within 30 s of this call's end, or the machine goes back and
# the run with it); 1: it died (its log's tail is printed). A run finished and recorded by an earlier call exits 0 at
# once. Env: G (.gpu), OUT, RUNS (/tmp/runs), DEVICE_ENV=0 for a dry run without the device's environment, SCENE
# (the folder under $G/scenes whose COLMAP model is used), FINISH_BACKEND (cuda), FINISH_COMPRESS (1).
set -u
cd "$(dirname "$0")/../.."
G=${G:-.gpu}
OUT=${OUT:-/tmp/ctgs_out}
RUNS=${RUNS:-/tmp/runs}
source benchmarks/device/lib.sh
mode=${1:?start or wait}
name=${2:?run name}
secs=${3:?seconds to wait}
shift 3
run=$RUNS/$name
mkdir -p "$RUNS" "$OUT"
device_env
if [[ $mode == start ]]; then
  rm -rf "$run" "$run.log"
  setsid nohup python3 -m ctgs train "$@" -o "$run" -q > "$run.log" 2>&1 < /dev/null &
  echo $! > "$run.pid"
  echo "started $name (pid $(cat "$run.pid")): ctgs train $* -o $run"
elif [[ $mode != wait ]]; then
  echo "bg.sh: the mode is start or wait, not $mode" >&2; exit 2
fi
[[ -f $run.pid ]] || { echo "bg.sh: no run $name under $RUNS (start it first, on this machine)" >&2; exit 2; }
pid=$(cat "$run.pid")
if [[ -f $run.done ]]; then echo "$name: finished and recorded by an earlier call"; exit 0; fi
t0=$(date +%s)
while true; do
  if [[ -f $run/train_summary.json ]] && ! kill -0 "$pid" 2>/dev/null; then
    echo "$name finished after $(( $(date +%s) - t0 )) s of this wait"
    tail -3 "$run.log"
    finish_run "$run" "$name" "$OUT"
    cp "$run.log" "$OUT/bg_$name.log"
    touch "$run.done"
    exit 0
  fi
  if ! kill -0 "$pid" 2>/dev/null; then
    echo "$name died:"; tail -20 "$run.log"; cp "$run.log" "$OUT/bg_$name.log" 2>/dev/null
    mkdir -p "$OUT/pipe_$name" && cp "$run/log.jsonl" "$OUT/pipe_$name/" 2>/dev/null
    exit 1
  fi
  if (( $(date +%s) - t0 >= secs )); then
    echo "$name still running after $secs s: $(tail -c 300 "$run/log.jsonl" 2>/dev/null | tail -1)"
    mkdir -p "$OUT/pipe_$name" && cp "$run/log.jsonl" "$OUT/pipe_$name/" 2>/dev/null
    exit 3
  fi
  sleep 5
done
