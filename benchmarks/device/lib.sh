# Shared by session.sh and bg.sh (sourced, not run): the device call's environment, and a finished run's
# export / compress / eval with its records copied out.

# device_env: the wheels the image lacks into /tmp/site, and the variables that make ctgs use what .gpu/ carries
# (prebuilt extensions, gsplat, the scene's COLMAP model). DEVICE_ENV=0 skips it (a dry run on the dev machine).
device_env() {
  [[ ${DEVICE_ENV:-1} == 0 ]] && return 0
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    "$G"/whl/*.whl || echo "wheel install failed"
  export PYTHONPATH="$PWD/benchmarks/device:$PWD:/tmp/site:$PWD/$G/py"
  export CTGS_PREBUILT=1 CTGS_CACHE_DIR="$PWD/$G/ctgs_cache" PYTHONUNBUFFERED=1 MAX_JOBS=16
  export GSPLAT_PREBUILT="$PWD/$G/gsplat_cuda.so" TORCH_CUDA_ARCH_LIST=9.0
  export CTGS_COLMAP_PICKLE="$PWD/$G/scenes/herzjesu25/colmap.pkl"
}

# finish_run RUN NAME DEST: export, compress (--jobs 8), eval both (PSNR/SSIM: the LPIPS weights do not travel), and
# the records into DEST/pipe_NAME.
finish_run() {
  local run=$1 name=$2 dest=$3 backend=${FINISH_BACKEND:-cuda}
  python3 -m ctgs export "$run" -o "$run/model" 2>&1 | tail -3
  python3 -m ctgs compress "$run/model" -o "$run/model-compressed" --jobs 8 2>&1 | tail -3
  python3 -m ctgs eval "$run" --model "$run/model" -o "$run/eval" --no-lpips --backend "$backend" 2>&1 | tail -3
  python3 -m ctgs eval "$run" --model "$run/model-compressed" -o "$run/eval-compressed" --no-lpips \
    --backend "$backend" 2>&1 | tail -3
  mkdir -p "$dest/pipe_$name"
  for f in log.jsonl config.toml train_summary.json model/manifest.json model-compressed/manifest.json \
      eval/metrics.json eval/per_image.csv eval-compressed/metrics.json; do
    [ -f "$run/$f" ] && cp "$run/$f" "$dest/pipe_$name/$(echo "$f" | tr / _)"
  done
  du -sh "$run/model" "$run/model-compressed" 2>/dev/null
  head -c 600 "$run/eval/metrics.json" 2>/dev/null; echo
}
