"""Data parallelism over devices: the env batch is split along a one-axis mesh named "envs",
parameters are replicated. `jax.jit` follows the input shardings (GSPMD), so the rollout
code itself is unchanged: each device steps its own slice of the envs, and the loop's
all-done test is the only cross-device reduction per control step.

Multi-host: after `jax.distributed.initialize()`, `jax.devices()` lists every host's devices,
each process passes the same host arrays, and results are gathered back to every process.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

AXIS = "envs"


def env_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh over `devices` (default: all devices, every host's after jax.distributed)."""
    return Mesh(np.asarray(jax.devices() if devices is None else devices), (AXIS,))


def local_mesh(devices: int = 0) -> Mesh:
    """The mesh over the first `devices` local devices (0: all of them); ValueError naming how
    many there are when `devices` is negative or more."""
    available = jax.local_device_count()
    if not 0 <= devices <= available:
        raise ValueError(f"devices={devices}: {available} local devices here (0: all of them)")
    return env_mesh(jax.local_devices()[:devices or available])


def check_batch(num_envs: int, mesh: Mesh) -> None:
    if num_envs % mesh.size:
        raise ValueError(f"num_envs={num_envs} is not divisible by the {mesh.size} devices it is sharded over; "
                         f"use a multiple of {mesh.size}")


def default_devices(batch: int, available: int) -> int:
    """The most of `available` devices that divide `batch` (1 always does)."""
    return max(d for d in range(1, available + 1) if batch % d == 0)


def parse_batch_devices(items: Sequence[str], available: int) -> list[tuple[int, int]]:
    """(envs, devices) per entry "B" (the most devices dividing B) or "B:D" (B envs over the
    first D devices); ValueError naming the bad entry and why."""
    out = []
    for item in items:
        parts = item.strip().split(":")
        if len(parts) > 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
            raise ValueError(f"--batch_sizes: {item!r} is not B or B:D with positive integers B (envs) "
                             f"and D (devices)")
        b = int(parts[0])
        d = int(parts[1]) if len(parts) == 2 else default_devices(b, available)
        if d > available:
            raise ValueError(f"--batch_sizes: {item!r} asks for {d} devices; {available} are available here")
        if b % d:
            raise ValueError(f"--batch_sizes: {item!r}: {b} envs cannot be split evenly over {d} devices")
        out.append((b, d))
    return out


def shard_batch(mesh: Mesh, tree: Any) -> Any:
    """Splits every array of `tree` along its leading (env) axis over the mesh."""
    return jax.device_put(tree, NamedSharding(mesh, P(AXIS)))


def replicated(mesh: Mesh) -> NamedSharding:
    """The sharding that puts a whole copy of an array on every device of `mesh`."""
    return NamedSharding(mesh, P())


def replicate(mesh: Mesh, tree: Any) -> Any:
    """A full copy of `tree` (parameters) on every device of the mesh."""
    if jax.process_count() > 1:  # committed single-device arrays cannot be sent to other hosts
        tree = jax.device_get(tree)
    return jax.device_put(tree, replicated(mesh))


def slot_constraint(mesh: Mesh):
    """A function `(tree, n)` that keeps every leaf batched over n env slots split over the
    mesh inside a jitted loop, and every other leaf whole on every device (`slot_placement`);
    identity on one device."""
    if mesh.size == 1:
        return lambda tree, n: tree
    return lambda tree, n: jax.tree.map(jax.lax.with_sharding_constraint, tree, slot_placement(mesh, tree, n))


def slot_placement(mesh: Mesh, tree: Any, n: int) -> Any:
    """Where `slot_constraint` puts each leaf of `tree` (arrays or their shapes): split over the
    mesh if batched over n env slots (leading axis n), else replicated, as is an empty leaf
    (XLA returns one replicated whatever its constraint)."""
    spec, whole = NamedSharding(mesh, P(AXIS)), replicated(mesh)
    split = lambda shape: len(shape) > 0 and shape[0] == n and 0 not in shape  # noqa: E731
    return jax.tree.map(lambda x: spec if split(np.shape(x)) else whole, tree)


def slot_specs(mesh: Mesh, tree: Any, n: int) -> Any:
    """The shapes of `tree` placed as `slot_constraint` places them: the inputs to lower a
    program at, which takes what another program, ending in that constraint, returned (a
    lowered program's output shapes carry no placement); `tree` itself on one device."""
    if mesh.size == 1:
        return tree
    return jax.tree.map(lambda x, where: jax.ShapeDtypeStruct(np.shape(x), x.dtype, sharding=where),
                        tree, slot_placement(mesh, tree, n))


def sync(name: str) -> None:
    """Across hosts, waits until every process reaches `name` (e.g. all have compiled, so that
    a timed batch does not include waiting for a slower process's compilation)."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)


def fetch(tree: Any) -> Any:
    """Host copies of (possibly sharded) arrays; across hosts, gathered on every process."""
    if jax.process_count() > 1:
        return multihost_utils.process_allgather(tree, tiled=True)
    return jax.device_get(tree)


def fetch_slice(tree: Any, index: tuple[slice, ...]) -> Any:
    """Host copies of `x[index]` for every array `x` of `tree` (`index`: slices with
    non-negative bounds, one per leading axis), copying only those elements off the devices:
    each device slices the part of its shard that falls inside `index` and sends that, and
    the host assembles the pieces. A collection's trajectories are recorded into buffers of
    the batch's longest time limit and padded env slots; what it keeps is a corner of them.
    Across hosts: gathered whole, then sliced."""
    return start_fetch_slice(tree, index)()


def start_fetch_slice(tree: Any, index: tuple[slice, ...]) -> Callable[[], Any]:
    """`fetch_slice` in two halves: this one queues the device-side slicing and starts the
    copies to the host, and returns the function that waits for them and assembles the host
    arrays. What the devices run next (queued after the slicing) then runs while the copies
    travel."""
    if jax.process_count() > 1:
        return lambda: jax.tree.map(lambda x: np.asarray(x)[index], fetch(tree))
    leaves, treedef = jax.tree.flatten(tree)
    leaves = [jax.numpy.asarray(x) for x in leaves]
    plans = [_slice_plan(x, index) for x in leaves]
    for _, plan in plans:
        for _, piece in plan:
            piece.copy_to_host_async()

    def assemble():
        out = []
        for x, (shape, plan) in zip(leaves, plans):
            if len(plan) == 1 and plan[0][0] == tuple(slice(0, n) for n in shape):
                out.append(np.asarray(plan[0][1]))  # one piece covers it: no second copy
                continue
            host = np.empty(shape, x.dtype)
            for where, piece in plan:
                host[where] = np.asarray(piece)
            out.append(host)
        return jax.tree.unflatten(treedef, out)

    return assemble


def _slice_plan(x: jax.Array, index: tuple[slice, ...]):
    """(the shape of `x[index]`, [(where in it, the device-side slice that fills it)]): one
    entry per distinct shard that overlaps `index`."""
    if len(index) > x.ndim or any(s.step not in (None, 1) or (s.start or 0) < 0 or (s.stop is not None and s.stop < 0)
                                  for s in index):
        raise ValueError(f"fetch_slice: {index} is not contiguous non-negative slices of the leading axes of an "
                         f"array of shape {x.shape}")
    index = tuple(index) + (slice(None),) * (x.ndim - len(index))
    want = [range(*s.indices(n)) for s, n in zip(index, x.shape)]
    plan, seen = [], set()
    for shard in x.addressable_shards:
        have = [range(*s.indices(n)) for s, n in zip(shard.index, x.shape)]
        lo = tuple(max(w.start, h.start) for w, h in zip(want, have))
        hi = tuple(min(w.stop, h.stop) for w, h in zip(want, have))
        if any(a >= b for a, b in zip(lo, hi)) or (lo, hi) in seen:
            continue  # outside the slice, or a replica of a piece already planned
        seen.add((lo, hi))
        local = tuple(slice(a - h.start, b - h.start) for a, b, h in zip(lo, hi, have))
        where = tuple(slice(a - w.start, b - w.start) for a, b, w in zip(lo, hi, want))
        plan.append((where, shard.data[local]))
    return tuple(len(r) for r in want), plan
