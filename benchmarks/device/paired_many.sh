#!/usr/bin/env bash
# Paired trainings on the device, several at once (run_many.py), with the CUDA tests and a smoke run of the
# training options no GPU test covers (exposure compensation, the depth-normal term, `ctgs render --maps`,
# `ctgs eval`'s gain columns) while they train; across one or two calls like many.sh:
#
#   bash benchmarks/device/paired_many.sh start JOBS SLOTS STOP_AFTER WAIT   start the jobs detached, run the checks,
#                                                                            wait up to WAIT s from this call's start
#   bash benchmarks/device/paired_many.sh wait WAIT                          wait up to WAIT s more (a later call)
#
# Returns at most 8 files: $OUT/checks.tgz (machine, tests, smoke, run_many's status, nvidia-smi samples, each job's
# output) and one $OUT/run_NAME.tgz per finished job (model.pt, config.toml, log.jsonl, train_summary.json; no
# checkpoints), which benchmarks/device/import_runs.py turns into benchmarks/paired.py's runs on the dev machine.
# Exit 0: all jobs ended; 3: some still run (call `wait` within 30 s). Env: G (.gpu), OUT, ROOT (/tmp/many),
# DEVICE_ENV=0 and SMOKE_ARGS for a dry run on the dev machine, TESTS_S (150; 0 skips the tests), SMOKE=0
# skips the smoke run.
set -u
cd "$(dirname "$0")/../.."
G=${G:-.gpu}
OUT=${OUT:-/tmp/ctgs_out}
ROOT=${ROOT:-/tmp/many}
R=/tmp/ctgs_checks
t0=$(date +%s)
stamp() { echo "== $(($(date +%s) - t0)) s: $*"; }
mode=${1:?start or wait}
mkdir -p "$OUT" "$R"
pack() {
  cp "$ROOT"/status.json "$ROOT"/*.log "$ROOT"/smi.csv "$ROOT"/run_many.out "$R/" 2>/dev/null
  tar czf "$OUT/checks.tgz" -C "$R" . 2>/dev/null
  for run in "$ROOT"/*/; do
    name=$(basename "$run")
    [[ -f $run/model.pt && ! -f $OUT/run_$name.tgz ]] || continue
    tar czf "$OUT/run_$name.tgz" -C "$run" model.pt config.toml log.jsonl train_summary.json 2>/dev/null
    echo "packed $name: $(du -h "$OUT/run_$name.tgz" | cut -f1)"
  done
}
if [[ $mode == start ]]; then
  jobs=${2:?jobs file} slots=${3:?slots} stop=${4:?stop after seconds} secs=${5:?seconds to wait}
  stamp "start $jobs"
  OUT=/tmp/many_pack bash benchmarks/device/many.sh start "$jobs" "$slots" "$stop" 0 > "$R/many_start.log" 2>&1
  source benchmarks/device/lib.sh
  device_env
  python3 - <<'PY' > "$R/machine.json"
import json, platform, subprocess, torch
p = torch.cuda.get_device_properties(0) if torch.cuda.is_available() else None
drv = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"], capture_output=True,
                     text=True).stdout.strip() if p else ""
print(json.dumps({"gpu": p.name if p else "none", "sms": p.multi_processor_count if p else 0, "driver": drv,
                  "torch": torch.__version__, "cuda": torch.version.cuda, "python": platform.python_version(),
                  "command": "benchmarks/device/paired_many.sh"}))
PY
  cat "$R/machine.json"
  if [[ ${TESTS_S:-150} != 0 ]]; then
    stamp "tests"
    CTGS_AGREEMENT_LOG="$R/agreement.jsonl" timeout "${TESTS_S:-150}" python3 -m pytest -q -ra -p no:cacheprovider \
      tests/render/test_cuda_backend.py -k "not compile_with_nvcc" > "$R/pytest_cuda.log" 2>&1
    tail -3 "$R/pytest_cuda.log"
    python3 benchmarks/cuda_agreement.py "$R/agreement.jsonl" --machine "$R/machine.json" -o "$R/cuda_agreement" \
      > /dev/null 2>&1 || echo "cuda_agreement.py failed"
  fi
  [[ ${SMOKE:-1} == 0 ]] || {
  stamp "smoke"
  S=/tmp/smoke
  rm -rf "$S"
  {
    set -x
    python3 -m ctgs train "$G/scenes/herzjesu25" -o "$S/run" -q ${SMOKE_ARGS:---backend cuda} --images images_8 \
      --preset fast --iterations 400 --set lambda_normal=0.05 &&
    grep -c '"type": "exposure"' "$S/run/log.jsonl" &&
    python3 -m ctgs render "$S/run" -o "$S/maps" --maps rgb,normal,depth ${SMOKE_ARGS:---backend cuda} &&
    ls "$S/maps" &&
    python3 -m ctgs export "$S/run" -o "$S/run/model" &&
    python3 -m ctgs eval "$S/run" --model "$S/run/model" -o "$S/eval" --no-lpips ${SMOKE_ARGS:---backend cuda} &&
    head -3 "$S/eval/per_image.csv" && echo "SMOKE OK"
    set +x
  } > "$R/smoke.log" 2>&1
  tail -4 "$R/smoke.log"
  cp "$S/run/log.jsonl" "$R/smoke_log.jsonl" 2>/dev/null; cp "$S/eval/metrics.json" "$R/smoke_metrics.json" 2>/dev/null
  }
  secs=$((secs - ($(date +%s) - t0)))
elif [[ $mode == wait ]]; then
  secs=${2:?seconds to wait}
else
  echo "paired_many.sh: the mode is start or wait, not $mode" >&2; exit 2
fi
stamp "waiting up to $secs s for the jobs"
t1=$(date +%s)
while [[ ! -f $ROOT/DONE ]] && (( $(date +%s) - t1 < secs )); do sleep 5; done
stamp "pack"
pack
python3 - "$ROOT/status.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
print({k: (j["state"], j.get("wall_s")) for k, j in d["jobs"].items()})
PY
[[ -f $ROOT/DONE ]] && exit 0
exit 3
