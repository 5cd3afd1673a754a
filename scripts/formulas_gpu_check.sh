#!/usr/bin/env bash
# GPU check of the shared leaf formulas (jaxrt/_src/formulas) in the Triton kernels: the kernel tests, and the
# GPU bench of the tree before and after, back to back in one device session.
#   prepare [BASE]  on the host, in a git checkout: snapshots of BASE (default 80cad43) in .snap/before and of
#                   HEAD in .snap/after (git archive; uncommitted work is not measured)
#   tests           on the GPU: the kernel tests of .snap/after (tests/test_gpu.py, tests/test_gpu_analytic.py,
#                   tests/test_gpu_compiles.py) and tests/test_formulas.py
#   bench [ROUND]   on the GPU: python -m jaxrt.bench.gpu on sphere, soup, bunny, dragon, sponza, sibenik (fast
#                   trees, no portable path), before then after (one call fits the 10-minute limit); run it twice
#                   (ROUND 1 and 2) on the same warm machine and compare each row's best of the two rounds
#                   (target: after within 3% of before)
# On the GPU machine, the wheels in .whl/ (jax-triton, trimesh) are installed as scripts/gpu_session.sh does, and
# the meshes are read from .data/ (JAXRT_DATA_DIR). Logs and JSON go to $OUT (or /tmp/out).
set -uo pipefail
mode=${1:-tests}
out=${OUT:-/tmp/out}
root=$PWD
if [ "$mode" = prepare ]; then
  base=${2:-80cad43}
  rm -rf .snap/before .snap/after && mkdir -p .snap/before .snap/after
  git archive "$base" jaxrt tests pyproject.toml | tar x -C .snap/before
  git archive HEAD jaxrt tests scripts pyproject.toml | tar x -C .snap/after
  echo "snapshots: before $(git rev-parse --short "$base"), after $(git rev-parse --short HEAD)"
  exit 0
fi
mkdir -p "$out"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
fi
export PYTHONUNBUFFERED=1 JAXRT_DATA_DIR=$root/.data
nvidia-smi --query-gpu=name,driver_version,clocks.sm,memory.used --format=csv
step() { local name=$1 limit=$2; shift 2; echo "=== $name: $*"; timeout "$limit" "$@" 2>&1 | tee "$out/$name.log"; echo "exit ${PIPESTATUS[0]}"; }
case $mode in
  tests)
    cd .snap/after && export PYTHONPATH=/tmp/site:$PWD
    step tests_gpu 540 python3 -m pytest tests/test_gpu.py tests/test_gpu_analytic.py tests/test_gpu_compiles.py \
      tests/test_formulas.py -x -q -p no:cacheprovider -rs
    ;;
  bench)
    round=${2:-1}
    for tree in before after; do
      (cd ".snap/$tree" && export PYTHONPATH=/tmp/site:$PWD && step "bench_${tree}_$round" 280 \
        python3 -m jaxrt.bench.gpu --scenes sphere,soup,bunny,dragon,sponza,sibenik --quality fast \
        --portable-rays 0 --repeats 5 --json "$out/bench_${tree}_$round.json")
    done
    ;;
  *) echo "unknown mode $mode (prepare, tests, bench)"; exit 2 ;;
esac
