#!/usr/bin/env bash
# One device session for the GPU kernel, run from the repository root of a CUDA machine that has the carried
# jax-triton wheel in .whl/ (and, for "peers", the parts of NVIDIA Warp packed by warp-for-device.sh):
#   check   the GPU tests, then the GPU bench with kernel variants and 10M-triangle builds
#   peers   the GPU bench with --peers (Warp's SAH and LBVH meshes on the same rays)
#   tests   every test of tests/test_gpu.py (the Triton-interpreter one included)
#   stage   only keep a carried .peers/warp.so.xz.part00 in /root/parts for a following "peers" call
# Logs and JSON go to $OUT (or /tmp/out).
set -uo pipefail
mode=${1:-check}
out=${OUT:-/tmp/out}
mkdir -p "$out"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
if [ -f .peers/warp.so.xz.part00 ]; then mkdir -p /root/parts && cp .peers/warp.so.xz.part00 /root/parts/; fi
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.max.sm,memory.used --format=csv
python3 -c "import jax, jax_triton, triton, numpy; print('jax', jax.__version__, 'triton', triton.__version__, 'jax-triton', jax_triton.__version__, 'numpy', numpy.__version__, jax.devices())"
case $mode in
  check)
    timeout 240 python3 -m pytest tests/test_gpu.py -q -p no:cacheprovider -rs -s -k "not interpreter" 2>&1 | tee "$out/tests.log"
    timeout 330 python3 -m jaxrt.bench.gpu --variants --build-sizes 10000000 --json "$out/bench_variants.json" 2>&1 | tee "$out/bench_variants.log"
    ;;
  peers)
    mkdir -p /root/wsite && tar xzf .peers/warp-py.tgz -C /root/wsite &&
      cat /root/parts/warp.so.xz.part00 .peers/warp.so.xz.part01 .peers/warp.so.xz.part02 | xz -d > /root/wsite/warp/bin/warp.so || exit 1
    export PYTHONPATH=$PYTHONPATH:/root/wsite
    timeout 500 python3 -m jaxrt.bench.gpu --peers --json "$out/bench_peers.json" 2>&1 | tee "$out/bench_peers.log"
    ;;
  tests)
    timeout 400 python3 -m pytest tests/test_gpu.py -v -p no:cacheprovider -rs -s --durations=5 2>&1 | tee "$out/tests.log"
    ;;
  stage) ls -la /root/parts ;;
esac
