#!/usr/bin/env bash
# Many worlds and many devices, one run on a host of four GPUs (device kind nvidia-h200-x4 or nvidia-h100-x4), from
# the repository root, with the wheels in .whl/ (jax-triton) as scripts/device_run.sh has them. About 6 minutes:
#   1. sharded       python -m jaxrt.bench.sharded: 16,777,216 camera rays into the 1M-triangle sphere, one device
#                    against rt.intersect_sharded over four, the rays in image order and with image rows dealt
#                    to the devices in turn; then 33,554,432 rays (the camera gives 33,558,849, which four devices
#                    do not divide)
#   2. worlds_devices python -m jaxrt.bench.worlds: 4,096 worlds, 128x128 and 64x64, rebuilt every step, on one
#                    device and split over four (rt.update_worlds with a mesh)
#   3. worlds_table  the worlds table on one GPU (CUDA_VISIBLE_DEVICES=0): 128x128 and 64x64; 256, 1,024 and 4,096
#                    worlds; rebuild and refit; the full step and a 10% step
#   4. tests_worlds  tests/test_worlds.py on the GPU (partial updates against full ones and the float64 oracle), if
#                    the budget has time left
# Every step has a time limit and the whole run a budget (BUDGET seconds, default 350): a step that would pass it is
# skipped. Each step prints its table (the last lines of its log) and its wall time; logs and JSON go to $OUT.
# SMOKE=1 runs tiny sizes (a check of the script on a CPU with XLA_FLAGS=--xla_force_host_platform_device_count=4).
set +x
set -uo pipefail
out=${OUT:-/tmp/out}
budget=${BUDGET:-350}
mkdir -p "$out"
SECONDS=0
if ls .whl/*.whl > /dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || echo "pip install of .whl/ failed: going on with what is installed"
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=index,name,memory.used,memory.total --format=csv,noheader
python3 -c "import jax; print('jax', jax.__version__, jax.devices())"
if python3 -c "import jax_triton" 2> /dev/null; then
  kernel=1
  echo "jax-triton found: the GPU kernel traces"
else
  kernel=0
  echo "WARNING: no jax-triton: the portable traversal traces, with smaller sizes below"
fi
echo "setup took ${SECONDS} s"

step() {
  local name=$1 limit=$2
  shift 2
  local left=$((budget - SECONDS))
  if [ "$left" -lt 30 ]; then
    echo "=== $name: skipped, ${SECONDS} s of the ${budget} s budget spent"
    return
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  echo "=== $name (limit ${limit} s): $*"
  local start=$SECONDS
  timeout "$limit" "$@" > "$out/$name.log" 2>&1
  local rc=$?
  grep -v -E "^(W|I|E)[0-9]{4} |UserWarning|warnings\.warn|^ *$" "$out/$name.log" | tail -n 40
  echo "=== $name: exit $rc after $((SECONDS - start)) s (run total ${SECONDS} s)"
}

triangles=1000000 sides=128,64
if [ -n "${SMOKE:-}" ]; then
  triangles=20000 rays=10000 odd=10202 worlds=16,32 big=16 sides=16
elif [ "$kernel" = 1 ]; then
  rays=16777216 odd=33554432 worlds=256,1024,4096 big=4096
else
  rays=4194304 odd=4198401 worlds=256,1024 big=1024
fi
step sharded 110 python3 -m jaxrt.bench.sharded --triangles "$triangles" --rays "$rays,$odd" --repeats 3 \
  --json "$out/sharded.json"
step worlds_devices 90 python3 -m jaxrt.bench.worlds --worlds "$big" --sides "$sides" --modes rebuild --devices 1,4 \
  --repeats 3 --json "$out/worlds_devices.json"
step worlds_table 200 env CUDA_VISIBLE_DEVICES=0 python3 -m jaxrt.bench.worlds --worlds "$worlds" --sides "$sides" \
  --modes rebuild,refit --repeats 3 --json "$out/worlds_table.json"
step tests_worlds 60 python3 -m pytest tests/test_worlds.py -q -p no:cacheprovider -x -rs
echo "done in ${SECONDS} s; logs and JSON in $out"
