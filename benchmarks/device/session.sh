#!/usr/bin/env bash
# One command on a GPU machine without network: CUDA tests with the agreement log, the kernel benchmark
# against gsplat, and timed paper-scale training on herzjesu25, each phase under its own time limit so that
# a failure or a slow phase leaves the others their time. Everything lands in $OUT/results.tgz plus
# $OUT/session.log (the device returns at most 8 files).
#
# What travels with it (an ignored folder named in `carry`, built on the dev machine; see
# docs/guide/gpu.md, "Running the device checks again"): $G/ctgs_cache (prebuilt extensions), $G/py/gsplat + $G/gsplat_cuda.so,
# $G/whl (wheels the image lacks), $G/scenes/herzjesu25 (ctgs sfm output + colmap.pkl). A training longer than a
# call: bg.sh. Both source lib.sh (the environment; a run's export, compress and eval).
#
#   benchmarks/device/session.sh [PHASES]   PHASES: any of tests,bench,fmad,ncu,train,probe,pipeline,pair
#                                           (default: tests,bench,ncu,train)
#   env: TRAIN_A_S, TRAIN_B_S (seconds of each training), BENCH_S, TESTS_S, TRAIN_PRESET, TRAIN_ITERS,
#        PROBE_S, PROBE_IT, PROBE_ARGS (more gpu_train_probe.py options),
#        PIPE_ITERS, PIPE_IMAGES, PIPE_S (seconds of each pipeline training), PIPE_METHODS (paper,2dgs: which
#        pipelines), PIPE_ARGS (more `ctgs train` options for each)
#        fmad: the CUDA tests and bench_cuda again with the kernels built with FMA contraction (CTGS_CUDA_FMAD=1;
#        prepare.sh prebuilds it), beside the bench phase's rows (BENCH_ARGS there: e.g. --sh-lanes-too)
#        pair: the method and the 2dgs baseline trained side by side in the background (bg.sh), started before every
#        other phase and waited for after them until PAIR_END seconds into the call (480), then each finished run
#        exported, evaluated and (the method's) compressed; a run still going is waited for by a later call
#        (`bg.sh wait paper|2dgs SECS`, within 30 s of this call's end). PAIR_PRESET (paper), PAIR_ARGS (more
#        `ctgs train` options for both). Their test renders come back as $OUT/renders_NAME.tar
#        (benchmarks/device/lpips_renders.py scores them).
set -u
PHASES=${1:-tests,bench,ncu,train}
G=${G:-.gpu}
OUT=${OUT:-/tmp/ctgs_out}
R=/tmp/ctgs_results
mkdir -p "$OUT" "$R"
exec > >(tee -a "$OUT/session.log") 2>&1
t_start=$(date +%s)
stamp() { echo "== $(($(date +%s) - t_start)) s: $*"; }
pack() { tar czf "$OUT/results.tgz" -C "$R" . 2>/dev/null; }  # after every phase: a killed call still returns

stamp "setup"
source benchmarks/device/lib.sh
device_env
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv
python3 - <<'EOF' > "$R/machine.json"
import json, platform, subprocess, torch
p = torch.cuda.get_device_properties(0)
drv = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"], capture_output=True,
                     text=True).stdout.strip()
commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
print(json.dumps({"gpu": p.name, "sms": p.multi_processor_count, "driver": drv, "torch": torch.__version__,
                  "cuda": torch.version.cuda, "python": platform.python_version(), "commit": commit or "?",
                  "command": "benchmarks/device/session.sh"}))
EOF
cat "$R/machine.json"
stamp "extensions"
python3 -c "
import torch
from ctgs.ops.ext import load_cpu
from ctgs.ops.ext_cuda import load_cuda
load_cpu(); load_cuda(); print('extensions ok')
" || echo "extension load FAILED"

BG=benchmarks/device/bg.sh
if [[ $PHASES == *pair* ]]; then
  stamp "pair: start"
  for m in paper 2dgs; do
    OUT=$R bash $BG start "$m" 0 "$G/scenes/${SCENE:-herzjesu25}" --backend cuda --preset "${PAIR_PRESET:-paper}" \
      ${PAIR_ARGS:-} $([[ $m == 2dgs ]] && echo --config configs/2dgs.toml) > "$R/start_$m.log" 2>&1
    head -n 1 "$R/start_$m.log"
  done
fi

if [[ $PHASES == *tests* ]]; then
  stamp "tests"
  rm -f "$R/agreement.jsonl"
  CTGS_AGREEMENT_LOG="$R/agreement.jsonl" timeout "${TESTS_S:-240}" python3 -m pytest -q -ra -p no:cacheprovider \
    tests/render/test_cuda_backend.py -k "not compile_with_nvcc" 2>&1 | tee "$R/pytest_cuda.log" | tail -40
  if grep -qE "[0-9]+ (failed|error)" "$R/pytest_cuda.log"; then
    stamp "tests: measuring run (record only)"
    rm -f "$R/agreement_all.jsonl"
    CTGS_AGREEMENT_LOG="$R/agreement_all.jsonl" CTGS_AGREEMENT_RECORD_ONLY=1 timeout 150 python3 -m pytest -q \
      -p no:cacheprovider tests/render/test_cuda_backend.py -k "not compile_with_nvcc" 2>&1 | tail -5
    python3 benchmarks/cuda_agreement.py "$R/agreement_all.jsonl" --machine "$R/machine.json" -o "$R/cuda_agreement_all" \
      > /dev/null
  fi
  python3 benchmarks/cuda_agreement.py "$R/agreement.jsonl" --machine "$R/machine.json" -o "$R/cuda_agreement" | tail -45
  # The backward kernel's other variant against the CPU too: the uncapped one (CTGS_CUDA_BWD_MIN_BLOCKS=1; the
  # default is 3 blocks per SM, at most 80 registers), so that both stay checked.
  stamp "tests: uncapped backward"
  CTGS_CUDA_BWD_MIN_BLOCKS=1 timeout 60 python3 -m pytest -q -p no:cacheprovider tests/render/test_cuda_backend.py \
    -k "not compile_with_nvcc" 2>&1 | tee "$R/pytest_cuda_mb1.log" | tail -3
  # A new kernel that failed its agreement test stays off for the rest of the call (its switch).
  if grep -q "FAILED.*aggregated" "$R/pytest_cuda.log"; then export CTGS_CUDA_TEX_AGG=0; echo "CTGS_CUDA_TEX_AGG=0 from here"; fi
pack
fi

if [[ $PHASES == *bench* ]]; then
  stamp "bench"
  timeout "${BENCH_S:-180}" python3 benchmarks/bench_cuda.py --out "$R" --profile ${BENCH_ARGS:-} 2>&1 | tee "$R/bench.log" | tail -40
pack
fi

if [[ $PHASES == *fmad* ]]; then
  stamp "fmad: tests"
  CTGS_CUDA_FMAD=1 timeout "${TESTS_S:-240}" python3 -m pytest -q -p no:cacheprovider tests/render/test_cuda_backend.py \
    -k "not compile_with_nvcc" 2>&1 | tee "$R/pytest_cuda_fmad.log" | tail -3
  stamp "fmad: bench"
  CTGS_CUDA_FMAD=1 timeout "${BENCH_S:-180}" python3 benchmarks/bench_cuda.py --out "$R/fmad" --tag fmad \
    ${BENCH_ARGS:-} 2>&1 | tee "$R/bench_fmad.log" | tail -20
pack
fi

if [[ $PHASES == *ncu* ]]; then
  stamp "ncu"
  NCU=$(command -v ncu || ls /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -1)
  for tex in "" "--textured"; do
    timeout "${NCU_S:-50}" "$NCU" --clock-control none -k regex:"forward_kernel|backward_kernel" --launch-skip 4 \
      --launch-count 2 --section SpeedOfLight --section LaunchStats --section Occupancy --section WarpStateStats \
      --section SchedulerStats --section MemoryWorkloadAnalysis --section ComputeWorkloadAnalysis \
      python3 benchmarks/device/ncu_target.py $tex > "$R/ncu${tex:+_textured}.txt" 2>&1
    echo "ncu${tex} rc=$?"; grep -E "forward_kernel|backward_kernel|Duration|Compute \(SM\) Throughput|Memory Throughput|Registers Per|Achieved Occupancy" \
      "$R/ncu${tex:+_textured}.txt" | head -24
  done
pack
fi

train() {  # name seconds extra-args...
  local name=$1 secs=$2; shift 2
  stamp "train $name (${secs} s)"
  rm -rf "/tmp/runs/$name"
  timeout -s TERM "$secs" python3 -m ctgs train "$G/scenes/${SCENE:-herzjesu25}" -o "/tmp/runs/$name" --backend cuda -q "$@" \
    2>&1 | tail -15
  echo "rc=${PIPESTATUS[0]}"
  mkdir -p "$R/train_$name"
  cp /tmp/runs/$name/log.jsonl /tmp/runs/$name/config.toml /tmp/runs/$name/summary.json "$R/train_$name/" 2>/dev/null
  tail -2 "/tmp/runs/$name/log.jsonl" 2>/dev/null
}
if [[ $PHASES == *train* ]]; then
  train paper "${TRAIN_A_S:-150}" --preset "${TRAIN_PRESET:-paper}" ${TRAIN_ITERS:+--iterations $TRAIN_ITERS}
  pack
  train 2dgs "${TRAIN_B_S:-100}" --preset "${TRAIN_PRESET:-paper}" --config configs/2dgs.toml \
    ${TRAIN_ITERS:+--iterations $TRAIN_ITERS}
  nvidia-smi --query-gpu=memory.used,clocks.sm --format=csv
fi

probe() {  # label seconds extra-env...
  local label=$1 secs=$2; shift 2
  stamp "probe $label (${secs} s)"
  env "$@" timeout -s TERM "$secs" python3 benchmarks/gpu_train_probe.py "$G/scenes/${SCENE:-herzjesu25}" --out "$R" \
    --label "$label" --preset paper --backend cuda --stop-at "${PROBE_IT:-2500}" --seconds "$((secs - 25))" \
    --profile-at 1210 --profile-steps 20 --set test_every=0 ${PROBE_ARGS:-} 2>&1 | tail -16
  echo "rc=${PIPESTATUS[0]}"
}
if [[ $PHASES == *probe* ]]; then
  probe new "${PROBE_S:-110}"
  pack
fi

pipeline() {  # name extra-args...: train, export, compress, eval (PSNR/SSIM: the LPIPS weights do not travel)
  local name=$1; shift
  local run=/tmp/runs/pipe_$name
  stamp "pipeline $name"
  rm -rf "$run"
  timeout -s TERM "${PIPE_S:-150}" python3 -m ctgs train "$G/scenes/${SCENE:-herzjesu25}" -o "$run" --backend cuda -q \
    --preset paper --iterations "${PIPE_ITERS:-6000}" --images "${PIPE_IMAGES:-images_2}" ${PIPE_ARGS:-} "$@" 2>&1 \
    | tail -5
  echo "train rc=${PIPESTATUS[0]}"
  stamp "pipeline $name: export, compress, eval"
  finish_run "$run" "$name" "$R"
}
if [[ $PHASES == *pipeline* ]]; then
  if [[ ${PIPE_METHODS:-paper,2dgs} == *paper* ]]; then pipeline paper; pack; fi
  if [[ ${PIPE_METHODS:-paper,2dgs} == *2dgs* ]]; then pipeline 2dgs --config configs/2dgs.toml; pack; fi
fi

if [[ $PHASES == *pair* ]]; then
  left=$(( ${PAIR_END:-480} - ($(date +%s) - t_start) ))
  stamp "pair: waiting up to $left s"
  FINISH_COMPRESS=1 OUT=$R bash $BG wait paper "$left" > "$R/wait_paper.log" 2>&1 &
  w1=$!
  FINISH_COMPRESS=0 OUT=$R bash $BG wait 2dgs "$left" > "$R/wait_2dgs.log" 2>&1 &
  w2=$!
  wait "$w1" "$w2"
  tail -n 4 "$R/wait_paper.log" "$R/wait_2dgs.log"
  mv "$R"/renders_*.tar "$OUT/" 2>/dev/null
fi

stamp "pack"
tar czf "$OUT/results.tgz" -C "$R" .
ls -la "$OUT"
stamp "done"
