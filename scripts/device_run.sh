#!/usr/bin/env bash
# One call on a CUDA machine: the core bench (GPU kernel and portable path), the gradient and instancing
# benches, and the GPU and gradient tests. Needs the wheels in .whl/ (jax-triton, trimesh) and the shared
# meshes copied to .data/ in the shared data layout. Logs and JSON go to $OUT (or /tmp/out).
#   bash scripts/device_run.sh core     core bench, gradient bench, GPU + gradient tests
#   bash scripts/device_run.sh more     instancing and curve benches
#   bash scripts/device_run.sh custom   custom-geometry bench and tests, curve bench, sharded bench (all GPUs)
#   bash scripts/device_run.sh final    GPU, custom-geometry, query and gradient tests; curve and instancing benches
#   bash scripts/device_run.sh kernels  custom-geometry bench (kernel rows), curve bench on the ponytail and bear
#   bash scripts/device_run.sh kerneltests  the analytic, multi-hit and curve kernel tests on the GPU
#   bash scripts/device_run.sh waves    the custom bench with its table of candidate waves (several candidates per
#                                       wave) at 65,536 and 1,048,576 rays, then the candidate-wave kernel tests
#   bash scripts/device_run.sh fused    the fused-ray kernel tests, then the GPU bench with its kernel variants and
#                                       intersect on fused rays and on a packed ray block (sphere, soup, bunny, dragon;
#                                       the meshes copied to .meshes/)
#   bash scripts/device_run.sh curvebatch  curve bench with deferred curve tests off and at two thresholds (each row
#                                          compared bit for bit with the first), then a few curve kernel tests
set -uo pipefail
part=${1:-core}
out=${OUT:-/tmp/out}
mkdir -p "$out"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 JAXRT_DATA_DIR=$PWD/.data
nvidia-smi --query-gpu=name,driver_version,clocks.sm,memory.used --format=csv
step() { local name=$1 limit=$2; shift 2; echo "=== $name: $*"; timeout "$limit" "$@" > "$out/$name.log" 2>&1; echo "exit $?"; }
case $part in
  core)
    step core_gpu 240 python3 -m jaxrt.bench --scenes sphere bunny dragon --triangles 1000000 --rays 1048576 \
      --no-embree --json "$out/core_gpu.json"
    step core_portable 150 python3 -m jaxrt.bench --backend portable --scenes sphere --triangles 1000000 \
      --rays 262144 --no-embree --json "$out/core_portable.json"
    step gradients 120 python3 -m jaxrt.bench.gradients --triangles 1000000 --rays 1048576 --json "$out/gradients.json"
    step tests 150 python3 -m pytest tests/test_gpu.py tests/test_gradients.py -q -p no:cacheprovider -rs \
      -k "not interpreter"
    ;;
  more)
    step instancing 200 python3 -m jaxrt.bench.instancing --json "$out/instancing.json"
    step curves 200 python3 -m jaxrt.bench.curves --json "$out/curves.json"
    ;;
  custom)
    step sharded 120 python3 -m jaxrt.bench.sharded --json "$out/sharded.json"
    step custom 150 python3 -m jaxrt.bench.custom --json "$out/custom.json"
    step custom_tests 120 python3 -m pytest tests/test_gradients_custom.py tests/test_query.py tests/test_gpu.py \
      -q -p no:cacheprovider -rs -k "not interpreter" -x
    step curves 180 python3 -m jaxrt.bench.curves --json "$out/curves.json"
    ;;
  final)
    step tests 260 python3 -m pytest tests/test_gpu.py tests/test_gradients_custom.py tests/test_query.py \
      tests/test_custom_geometry.py tests/test_multi_hit.py tests/test_gradients_curves.py -q -p no:cacheprovider \
      -rs -k "not interpreter"
    step curves 200 python3 -m jaxrt.bench.curves --scenes ponytail bear --settings 8,3 4,2 --tubes 6,2 \
      --json "$out/curves.json"
    step instancing 120 python3 -m jaxrt.bench.instancing --json "$out/instancing.json"
    ;;
  kernels)
    step custom 200 python3 -m jaxrt.bench.custom --json "$out/custom.json"
    step curves 380 python3 -m jaxrt.bench.curves --scenes ponytail bear --settings 8,3 --tubes 6,2 \
      --json "$out/curves.json"
    ;;
  fused)
    step fused_tests 200 python3 -m pytest tests/test_gpu_fused_rays.py tests/test_gpu.py -q -p no:cacheprovider -rs \
      -k "not interpreter" -x
    step instanced_tests 150 python3 -m pytest tests/test_gpu_instanced.py -q -p no:cacheprovider -rs \
      -k "not interpreter" -x
    step bench_gpu 200 python3 -m jaxrt.bench.gpu --variants ray-block --repeats 5 --portable-rays 262144 --meshes .meshes \
      --scenes sphere,soup,bunny,dragon --quality fast --json "$out/bench_gpu.json"
    ;;
  kerneltests)
    step kernel_tests 560 python3 -m pytest tests/test_gpu_analytic.py tests/test_gpu_multihit.py \
      tests/test_gpu_curves.py -q -p no:cacheprovider -rs -k "not interpreter" --durations=10
    ;;
  waves)
    step custom_65k 200 python3 -m jaxrt.bench.custom --repeats 20 --waves 1,4 4,16 16,16 --json "$out/custom_65k.json"
    step custom_1m 200 python3 -m jaxrt.bench.custom --repeats 10 --rays 1048576 --waves 4,16 \
      --json "$out/custom_1m.json"
    [ -n "${NO_TESTS:-}" ] || step waves_tests 240 python3 -m pytest tests/test_gpu_waves.py -q -p no:cacheprovider \
      -rs --durations=5 tests/test_gpu_analytic.py::test_user_functions_take_the_kernel_in_candidate_waves \
      -k "not interpreter"
    ;;
  curvebatch)
    step curvebatch 320 python3 -m jaxrt.bench.curves --scenes ponytail bear --settings 8,3 --curve-batch 0 16 8 \
      --tubes 6,2 --no-generic --json "$out/curvebatch.json"
    step curvebatch_tests 180 python3 -m pytest tests/test_gpu_curves.py -q -p no:cacheprovider -rs --durations=5 \
      -k "not interpreter and (test_every_basis_and_cap and bezier-4-sphere or kinked)"
    ;;
esac
for f in "$out"/*.log; do echo "##### $f"; tail -n 40 "$f"; done
