#!/usr/bin/env bash
# Prepare, on the dev machine (no GPU), the folder a device call carries (.gpu/, ignored by git):
#   .gpu/ctgs_cache   ctgs_cpu / ctgs_cuda built for the device's Python 3.12 + torch 2.11.0+cu130, sm_90
#   .gpu/py/gsplat    gsplat 1.5.3's Python package, .gpu/gsplat_cuda.so its extension built the same way
#   .gpu/whl          wheels the device image lacks (OpenImageIO, tomli_w, pygltflib)
#   .gpu/scenes/NAME  `ctgs sfm` output (images/ at full size, images_N/ where present, sparse/0 placeholders) +
#                     colmap.pkl; NAME is the scene folder's name, which the device scripts take as SCENE
#                     (herzjesu25 by default)
# The device has no network and 15 minutes; building there would cost ~4 of them (gsplat's JIT build alone).
# Versions: the device tool's KINDS.md (python3 3.12, torch 2.11.0+cu130, nvcc 13.0); check them in the first
# call. Usage: benchmarks/device/prepare.sh SCENE_DIR (a folder made by `ctgs sfm`); WORK=/work/gpu by default;
# GSPLAT=0 skips gsplat (only bench_cuda.py and the gsplat trainers need it).
set -euo pipefail
SCENE=${1:?scene folder made by ctgs sfm}
NAME=$(basename "$(cd "$SCENE" && pwd)")
WORK=${WORK:-/work/gpu}
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
G=$ROOT/.gpu
PY312=${PY312:-$(ls -d /root/.pyenv/versions/3.12*/bin/python3.12 | head -1)}
mkdir -p "$WORK/wheels" "$G/whl" "$G/scenes"
grep -qx "/.gpu/" "$ROOT/.git/info/exclude" 2>/dev/null || echo "/.gpu/" >> "$ROOT/.git/info/exclude"
dl() { python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$1" "${@:2}"; }
# 1. A Python 3.12 venv with the device's torch (PyPI's 2.11.0 is the cu130 build).
if [ ! -x "$WORK/venv312/bin/python" ]; then
  "$PY312" -m venv "$WORK/venv312"
  dl "$WORK/wheels" torch==2.11.0 gsplat==1.5.3
  "$WORK/venv312/bin/pip" install -q "$WORK"/wheels/torch-2.11.0-*.whl numpy ninja packaging rich jaxtyping typing_extensions
fi
export CUDA_HOME=${CUDA_HOME:-/usr/local/cuda} TORCH_CUDA_ARCH_LIST=9.0
# 2. ctgs's extensions, into the cache folder ctgs reads under CTGS_PREBUILT=1 (ctgs.ops.ext.load_prebuilt).
CTGS_CACHE_DIR="$G/ctgs_cache" MAX_JOBS=2 "$WORK/venv312/bin/python" "$ROOT/benchmarks/device/build_extensions.py"
# ... and ctgs_cuda again with FMA contraction (CTGS_CUDA_FMAD=1 selects it there; a build key of its own)
CTGS_CUDA_FMAD=1 CTGS_CACHE_DIR="$G/ctgs_cache" MAX_JOBS=2 "$WORK/venv312/bin/python" \
  "$ROOT/benchmarks/device/build_extensions.py"
find "$G/ctgs_cache" -type f ! -name "*.so" ! -name ".ctgs-built" ! -name "prebuilt.json" -delete
# 3. gsplat: its own JIT build (every kernel, ~30 min on 2 cores), then only the package and the .so travel.
if [[ ${GSPLAT:-1} == 1 && ! -f "$G/gsplat_cuda.so" ]]; then
  ls "$WORK"/wheels/gsplat-1.5.3-*.whl >/dev/null 2>&1 || dl "$WORK/wheels" gsplat==1.5.3
  rm -rf "$WORK/gs" && mkdir -p "$WORK/gs" && (cd "$WORK/gs" && unzip -q "$WORK"/wheels/gsplat-1.5.3-*.whl)
  (cd "$WORK/gs" && TORCH_EXTENSIONS_DIR="$WORK/ext_build" MAX_JOBS=2 "$WORK/venv312/bin/python" -c \
    "from gsplat.cuda._backend import _C; print(_C)")
  cp "$WORK/ext_build/gsplat_cuda/gsplat_cuda.so" "$G/gsplat_cuda.so"
  rm -rf "$G/py/gsplat" && mkdir -p "$G/py" && (cd "$WORK/gs" && tar cf - --exclude="csrc" gsplat) | (cd "$G/py" && tar xf -)
fi
# 4. Wheels the image lacks.
dl "$G/whl" OpenImageIO tomli_w pygltflib
# 5. The scene: full-size images, the model pickled (pycolmap's wheel is 38 MB), placeholder model files.
mkdir -p "$G/scenes/$NAME/sparse/0"
cp -r "$SCENE/images" "$G/scenes/$NAME/"
for d in images_2 images_4 images_8; do  # images_2: the pipeline phase; images_4/8: small runs (many.sh)
  if [ -d "$SCENE/$d" ]; then cp -r "$SCENE/$d" "$G/scenes/$NAME/"; fi
done
for f in cameras images points3D; do : > "$G/scenes/$NAME/sparse/0/$f.bin"; done
"$ROOT/.venv/bin/python" -c "
import pickle, sys
from ctgs.scene.colmap import read_colmap_model, find_model_dir
pickle.dump(read_colmap_model(find_model_dir(sys.argv[1])), open(sys.argv[2], 'wb'))" "$SCENE" \
  "$G/scenes/$NAME/colmap.pkl"
du -sh "$G"/*
