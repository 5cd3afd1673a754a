"""Several processes (``jax.distributed``): two CPU processes on this machine, two devices each, trace rays split
over the four devices of both with ``rt.intersect_sharded`` and get the hits of one process's plain call; and
``rt.update_worlds`` splits worlds over the same four devices.

The processes talk over loopback only (a free port on 127.0.0.1) and are killed after a bounded time.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap

_WORKER = textwrap.dedent(
    """
    import sys

    import jax

    process, port = int(sys.argv[1]), sys.argv[2]
    jax.distributed.initialize(
        coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=process, initialization_timeout=60
    )
    import numpy as np
    from jax.experimental import multihost_utils

    import jaxrt as rt
    from test_sharding import _assert_same, _scene_and_rays

    assert jax.process_count() == 2 and jax.device_count() == 4 and jax.local_device_count() == 2, jax.devices()
    structure, rays = _scene_and_rays(1001, seed=2)  # the same rays in both processes; 1001 = 4 x 250.25
    intersector = rt.Intersector(rt.tags.triangle_data)
    reference = intersector.intersect(rays, structure)  # this process alone, one device
    out = rt.intersect_sharded(intersector, rays, structure)  # all four devices of both processes
    assert not out.distance.is_fully_addressable
    everything = multihost_utils.process_allgather(out, tiled=True)
    assert int((np.asarray(reference.primitive_id) >= 0).sum()) > 100
    _assert_same(everything, reference)

    # Seven worlds over the four devices of both processes (padded to eight): the selected ones updated.
    mask = np.array([True, False, True, False, True, True, False])
    previous, x = np.full(7, -1.0, np.float32), np.arange(7, dtype=np.float32)
    worlds = rt.update_worlds(lambda v: 2 * v, mask, previous, x, mesh=rt.device_mesh(None, "worlds"))
    np.testing.assert_array_equal(multihost_utils.process_allgather(worlds, tiled=True), np.where(mask, 2 * x, -1))
    print(f"process {process} ok", flush=True)
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_trace_as_one():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(__file__), env.get("PYTHONPATH", "")])
    port = str(_free_port())
    workers = [
        subprocess.Popen(
            [sys.executable, "-c", _WORKER, str(i), port],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(2)
    ]
    outputs = []
    try:
        for worker in workers:
            outputs.append(worker.communicate(timeout=240)[0])
    finally:
        for worker in workers:
            if worker.poll() is None:
                worker.kill()
                worker.communicate()
    for i, (worker, output) in enumerate(zip(workers, outputs, strict=True)):
        assert worker.returncode == 0 and f"process {i} ok" in output, f"process {i}:\n{output}"
