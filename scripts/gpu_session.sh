#!/usr/bin/env bash
# One device session for the GPU kernel, run from the repository root of a CUDA machine that has the carried
# wheels in .whl/ (jax-triton; trimesh for the real meshes) and, for "peers", the parts of NVIDIA Warp packed by
# warp-for-device.sh. The Warp library is larger than one transfer, so it goes over in two calls: a first call
# that carries .peers/warp.so.xz.part00 keeps it in /root/parts; the "peers" call carries the other parts.
#   check   GPU tests (kernel, build quality, chunking), the build's stage timings, a 100M-ray intersect call,
#           10M-triangle builds
#   peers   the GPU bench with --peers (Warp SAH and LBVH; Embree where embreex is installed) on the
#           procedural scenes and on the real meshes carried in .meshes/, fast and high-quality trees
#   tests   every test of tests/test_gpu.py (the Triton-interpreter one included)
#   variants  GPU tests, then kernel variants (layouts, code generation) on the procedural scenes, bunny, Sponza
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
    timeout 420 python3 -m pytest tests/test_gpu.py tests/test_bvh_quality.py tests/test_sharding.py -q \
      -p no:cacheprovider -rs -k "not interpreter" 2>&1 | tee "$out/tests.log"
    timeout 200 python3 scripts/build_profile.py 2>&1 | tee "$out/build_profile.log"
    timeout 200 python3 -m jaxrt.bench.gpu --scenes "" --build-sizes 10000000 --repeats 5 --huge-rays 100000001 \
      --json "$out/bench_check.json" 2>&1 | tee "$out/bench_check.log"
    ;;
  peers)
    mkdir -p /root/wsite && tar xzf .peers/warp-py.tgz -C /root/wsite &&
      cat /root/parts/warp.so.xz.part00 .peers/warp.so.xz.part01 .peers/warp.so.xz.part02 | xz -d > /root/wsite/warp/bin/warp.so || exit 1
    export PYTHONPATH=$PYTHONPATH:/root/wsite
    timeout 220 python3 -m jaxrt.bench.gpu --peers --repeats 5 --json "$out/bench_peers.json" 2>&1 | tee "$out/bench_peers.log"
    timeout 300 python3 -m jaxrt.bench.gpu --peers --repeats 5 --portable-rays 0 --meshes .meshes \
      --scenes bunny,dragon,sponza,sibenik,bunny-1M,dragon-1M --json "$out/bench_meshes.json" 2>&1 | tee "$out/bench_meshes.log"
    ;;
  tests)
    timeout 400 python3 -m pytest tests/test_gpu.py -v -p no:cacheprovider -rs -s --durations=5 2>&1 | tee "$out/tests.log"
    ;;
  variants)
    timeout 420 python3 -m pytest tests/test_gpu.py -q -p no:cacheprovider -rs -k "not interpreter" 2>&1 | tee "$out/tests.log"
    timeout 400 python3 -m jaxrt.bench.gpu --variants --quality fast --repeats 3 --portable-rays 262144 --meshes .meshes \
      --scenes sphere,soup,bunny,sponza --json "$out/bench_variants.json" 2>&1 | tee "$out/bench_variants.log"
    ;;
esac
