"""MJX tabletop manipulation suites (LIBERO's counterparts): robot, scene, tasks, camera,
scripted experts and demonstrations."""

import contextlib as _contextlib
import io as _io
import os as _os

# MJX on CPU is ~13x slower with XLA's new CPU fusion emitters; the flag must be set before
# JAX starts its CPU backend. Appended to any user value, never overriding an explicit one.
_FLAG = "--xla_cpu_use_fusion_emitters=false"
if "xla_cpu_use_fusion_emitters" not in _os.environ.get("XLA_FLAGS", ""):
    _os.environ["XLA_FLAGS"] = (_os.environ.get("XLA_FLAGS", "") + " " + _FLAG).strip()

# mujoco.mjx prints a notice when the optional GPU-only Warp backend is absent; we use MJX's
# JAX implementation, so keep that notice out of users' logs.
with _contextlib.redirect_stdout(_io.StringIO()):
    from mujoco import mjx as _mjx  # noqa: F401
