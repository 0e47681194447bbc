"""MJX tabletop manipulation suites (LIBERO's counterparts): robot, scene, tasks, camera,
scripted experts and demonstrations."""

import contextlib as _contextlib
import io as _io

# MJX on CPU is ~13x slower with XLA's new CPU fusion emitters: switch them off before JAX
# starts its backends (see envs/_xla.py for when the flag is, and is not, set).
from envs import _xla

_xla.configure()
_xla.cholesky_without_lapack_on_cpu()

# mujoco.mjx prints a notice when the optional GPU-only Warp backend is absent; we use MJX's
# JAX implementation, so keep that notice out of users' logs.
with _contextlib.redirect_stdout(_io.StringIO()):
    from mujoco import mjx as _mjx  # noqa: F401
