# Shared by session.sh and bg.sh (sourced, not run): the device call's environment, and a finished run's
# export / compress / eval with its records copied out.

# device_env: the wheels the image lacks into /tmp/site, and the variables that make ctgs use what .gpu/ carries
# (prebuilt extensions, gsplat, the COLMAP model of the scene $G/scenes/$SCENE, herzjesu25 by default). DEVICE_ENV=0
# skips it (a dry run on the dev machine). The wheels are installed once per machine.
device_env() {
  [[ ${DEVICE_ENV:-1} == 0 ]] && return 0
  [[ -f /tmp/site/.ctgs-wheels ]] || { python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/site "$G"/whl/*.whl && touch /tmp/site/.ctgs-wheels; } || echo "wheel install failed"
  export PYTHONPATH="$PWD/benchmarks/device:$PWD:/tmp/site:$PWD/$G/py"
  export CTGS_PREBUILT=1 CTGS_CACHE_DIR="$PWD/$G/ctgs_cache" PYTHONUNBUFFERED=1 MAX_JOBS=16
  export GSPLAT_PREBUILT="$PWD/$G/gsplat_cuda.so" TORCH_CUDA_ARCH_LIST=9.0
  export CTGS_COLMAP_PICKLE="$PWD/$G/scenes/${SCENE:-herzjesu25}/colmap.pkl"
}

# finish_run RUN NAME DEST: export, compress (--jobs 8; FINISH_COMPRESS=0 skips it), eval both (PSNR/SSIM: the LPIPS
# weights do not travel), and the records into DEST/pipe_NAME, with the test renders as DEST/renders_NAME.tar (LPIPS is
# scored from them on the dev machine: benchmarks/device/lpips_renders.py).
finish_run() {
  local run=$1 name=$2 dest=$3 backend=${FINISH_BACKEND:-cuda} t0=$(date +%s)
  python3 -m ctgs export "$run" -o "$run/model" 2>&1 | tail -3
  python3 -m ctgs eval "$run" --model "$run/model" -o "$run/eval" --no-lpips --backend "$backend" 2>&1 | tail -3
  echo "$name: export and eval in $(( $(date +%s) - t0 )) s"
  mkdir -p "$dest/pipe_$name"
  tar cf "$dest/renders_$name.tar" -C "$run/eval" renders 2>/dev/null
  if [[ ${FINISH_COMPRESS:-1} == 1 ]]; then
    t0=$(date +%s)
    python3 -m ctgs compress "$run/model" -o "$run/model-compressed" --jobs 8 2>&1 | tail -3
    python3 -m ctgs eval "$run" --model "$run/model-compressed" -o "$run/eval-compressed" --no-lpips \
      --backend "$backend" 2>&1 | tail -3
    echo "$name: compress and its eval in $(( $(date +%s) - t0 )) s"
  fi
  for f in log.jsonl config.toml train_summary.json model/manifest.json model-compressed/manifest.json \
      eval/metrics.json eval/per_image.csv eval-compressed/metrics.json; do
    [ -f "$run/$f" ] && cp "$run/$f" "$dest/pipe_$name/$(echo "$f" | tr / _)"
  done
  du -sh "$run/model" "$run/model-compressed" 2>/dev/null
  head -c 600 "$run/eval/metrics.json" 2>/dev/null; echo
}

# collect DEST: everything under DEST but the renders tars into DEST/records.tgz (a call returns at most 8 files).
collect() {
  local dest=$1
  (cd "$dest" && tar czf records.tgz --exclude='renders_*.tar' --exclude=records.tgz . && \
    find . -mindepth 1 ! -name records.tgz ! -name 'renders_*.tar' -delete)
  ls -la "$dest"
}
