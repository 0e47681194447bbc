"""`sharding.fetch_slice` copies a corner of sharded arrays to the host: the same values as
slicing the whole host copy, for arrays split over 2 (virtual CPU) devices, replicated, or
on one device, where the corner lies in one shard, spans both or is empty.

The device count is fixed when JAX starts, so the check runs in its own process."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import jax, numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P
from heisd_jax import sharding

mesh = sharding.env_mesh()
assert mesh.size == 2
x = np.arange(5 * 6 * 3, dtype=np.float32).reshape(5, 6, 3)
placed = {"split": jax.device_put(x, NamedSharding(mesh, P(None, "envs"))),
          "replicated": sharding.replicate(mesh, x), "one_device": jax.device_put(x)}
y = np.arange(6, dtype=np.int32)
ys = sharding.shard_batch(mesh, y)
for index in [(slice(0, 5), slice(0, 6)), (slice(0, 3), slice(0, 2)), (slice(0, 2), slice(0, 4)),
              (slice(1, 4), slice(2, 5)), (slice(0, 0), slice(0, 6)), (slice(0, 3),)]:
    for name, a in placed.items():
        got = sharding.fetch_slice({"a": a, "b": (a,)}, index)
        for g in (got["a"], got["b"][0]):
            assert g.dtype == x.dtype and g.shape == x[index].shape, (name, index, g.shape)
            np.testing.assert_array_equal(g, x[index], err_msg=f"{name} {index}")
for n in (0, 2, 3, 6):
    np.testing.assert_array_equal(sharding.fetch_slice(ys, (slice(0, n),)), y[:n])
for bad in [(slice(0, 4, 2),), (slice(-2, None),), (slice(0, 1),) * 4]:
    try:
        sharding.fetch_slice(placed["split"], bad)
    except ValueError as e:
        assert "fetch_slice" in str(e) and "(5, 6, 3)" in str(e), e
    else:
        raise AssertionError(f"{bad} accepted")
print("OK")
"""


def test_fetch_slice_equals_slicing_the_host_copy():
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip())
    r = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.split()[-1] == "OK", r.stderr[-3000:]
