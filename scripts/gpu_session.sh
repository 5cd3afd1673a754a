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
#   instanced the instanced-kernel tests and the instancing bench (kernel and portable paths, batched scenes)
#   flat      the flat kernel of this tree against an earlier one (sphere, soup, bunny), then the GPU tests
#   programs  the instancing bench without the flattened scene, the kernel also under several program caps
#   tree      tree quality: the GPU bench on sphere, Sponza, bunny, Sibenik, dragon with the three triangle
#             build qualities (Warp beside them when its parts are here, as for "peers"), and the instancing bench
#             with the SAH and the LBVH instance trees (JSON: bench_tree.json, instancing_tree.json)
#   features  the GPU tests of the kernel, then the normal-tag, motion and point-query tests on the GPU backend
#   points    the point-query bench (closest point, signed distance, 256^3 and 512^3 sdf_grid) on the GPU point
#             kernels (--backend gpu) with Warp's mesh queries beside it
#   points_tests  the point-query tests on the GPU (the kernels against the portable walks and the brute force)
#   profile   Nsight Compute profiles (--set full) of one warm launch per SCENE:RAYS:TRACER in $PROFILES
#             (scripts/kernel_profile.py runs the tracer; Warp tracers need the reassembled Warp), then the
#             table of scripts/kernel_profile.py --report
# "instanced" and "flat" run from snapshots of committed trees, so that uncommitted work in the working tree
# cannot change what is measured: .snap/after (git archive HEAD jaxrt tests scripts pyproject.toml) and, for
# "flat", .snap/before (git archive <commit> jaxrt); the bunny is read from .data/stanford-bunny/.
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
root=$PWD
step() { local name=$1 limit=$2; shift 2; echo "=== $name: $*"; timeout "$limit" "$@" 2>&1 | tee "$out/$name.log"; echo "exit ${PIPESTATUS[0]}"; }
case $mode in
  instanced)
    cd .snap/after && export PYTHONPATH=/tmp/site:$PWD JAXRT_DATA_DIR=$root/.data
    step tests_instanced 150 python3 -m pytest tests/test_gpu_instanced.py -q -p no:cacheprovider -rs -x --durations=5
    step instancing 330 python3 -m jaxrt.bench.instancing --json "$out/instancing.json"
    ;;
  flat)
    for tree in before after; do
      (cd ".snap/$tree" && export PYTHONPATH=/tmp/site:$PWD JAXRT_DATA_DIR=$root/.data && step "flat_$tree" 170 \
        python3 -m jaxrt.bench.gpu --scenes sphere,soup,bunny --quality fast --portable-rays 0 --repeats 5 \
        --json "$out/flat_$tree.json")
    done
    cd .snap/after && export PYTHONPATH=/tmp/site:$PWD
    step tests_gpu 230 python3 -m pytest tests/test_gpu.py -q -p no:cacheprovider -rs -k "not interpreter"
    ;;
  programs)
    cd .snap/after && export PYTHONPATH=/tmp/site:$PWD
    step programs 400 python3 -m jaxrt.bench.instancing --max-flat 0 --programs 2048,4096,8192,32768 \
      --json "$out/programs.json"
    ;;
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
  tree)
    # Tree quality: the triangle build qualities (trace rows, build ms at 1M triangles, SAH cost) with Warp
    # beside them, then the island with the SAH and the LBVH instance trees. Under 8 minutes.
    peers=""
    if [ -f /root/parts/warp.so.xz.part00 ] && [ -f .peers/warp.so.xz.part01 ]; then
      mkdir -p /root/wsite && tar xzf .peers/warp-py.tgz -C /root/wsite &&
        cat /root/parts/warp.so.xz.part00 .peers/warp.so.xz.part01 .peers/warp.so.xz.part02 | xz -d > /root/wsite/warp/bin/warp.so &&
        export PYTHONPATH=$PYTHONPATH:/root/wsite && peers=--peers
    fi
    step bench_tree 300 python3 -m jaxrt.bench.gpu $peers --repeats 5 --portable-rays 0 --meshes .meshes \
      --scenes sphere,sponza,bunny,sibenik,dragon --quality fast,high,sah --json "$out/bench_tree.json"
    step instancing_tree 160 python3 -m jaxrt.bench.instancing --repeats 3 --scenes 64 --instance-quality high,fast \
      --json "$out/instancing_tree.json"
    ;;
  features)
    step tests_gpu 330 python3 -m pytest tests/test_gpu.py tests/test_gpu_instanced.py -q -p no:cacheprovider -rs \
      -k "not interpreter" --durations=5
    step tests_features 200 python3 -m pytest tests/test_normals.py tests/test_motion.py tests/test_point_queries.py \
      tests/test_cpu_backend.py -q -p no:cacheprovider -rs --durations=5
    ;;
  points)
    mkdir -p /root/wsite && tar xzf .peers/warp-py.tgz -C /root/wsite &&
      cat /root/parts/warp.so.xz.part00 .peers/warp.so.xz.part01 .peers/warp.so.xz.part02 | xz -d > /root/wsite/warp/bin/warp.so || exit 1
    export PYTHONPATH=$PYTHONPATH:/root/wsite JAXRT_DATA_DIR=$root/.data
    step points 540 python3 -m jaxrt.bench.points --peers --backend gpu --scenes sphere bunny --triangles 1000000 \
      --points 1048576 --reference-points 256 --repeats 3 --grid 256 512 --json "$out/points.json"
    ;;
  points_tests)
    export JAXRT_DATA_DIR=$root/.data
    step tests_points 540 python3 -m pytest tests/test_gpu_points.py tests/test_point_backends.py \
      tests/test_point_queries.py -q -p no:cacheprovider -rs -x --durations=5
    ;;
  profile)
    if [ -f .peers/warp-py.tgz ]; then
      mkdir -p /root/wsite && tar xzf .peers/warp-py.tgz -C /root/wsite &&
        cat /root/parts/warp.so.xz.part00 .peers/warp.so.xz.part01 .peers/warp.so.xz.part02 | xz -d > /root/wsite/warp/bin/warp.so || exit 1
      export PYTHONPATH=$PYTHONPATH:/root/wsite
    fi
    export XLA_PYTHON_CLIENT_PREALLOCATE=false
    mkdir -p "$out/ncu"
    for spec in ${PROFILES:-bunny:primary:binary}; do
      IFS=: read -r scene rays tracer <<< "$spec"
      case $tracer in warp*) kernel='regex:closest|anyhit' ;; wide*) kernel=regex:trace_wide_kernel ;; *) kernel=regex:trace_kernel ;; esac
      name=${scene}_${rays}_${tracer}
      echo "=== $name"
      # ncu crashed (SIGSEGV) on about half of the launches of the same command: up to four tries.
      for try in 1 2 3 4; do
        timeout "${PROFILE_LIMIT:-150}" ncu --clock-control none --set full -k "$kernel" --launch-skip 1 \
          --launch-count 1 -f -o "/tmp/$name" python3 scripts/kernel_profile.py --scene "$scene" --rays "$rays" \
          --tracer "$tracer" --meshes .meshes > "/tmp/$name.log" 2>&1
        code=$?; echo "try $try: exit $code"; [ $code = 0 ] && break
      done
      grep -v "^==PROF==" "/tmp/$name.log" | tail -2
      ncu --import "/tmp/$name.ncu-rep" --page raw --csv > "$out/ncu/$name.csv" 2>&1
      ncu --import "/tmp/$name.ncu-rep" --page details > "/tmp/$name.txt" 2>&1
    done
    (cd /tmp && tar czf "$out/ncu_details.tgz" ./*.txt)
    python3 scripts/kernel_profile.py --report "$out/ncu" | tee "$out/profile_table.md"
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
