"""heisd-jax: hybrid speculative decoding for VLA policies, evaluated in batched MJX envs."""

import envs as _envs  # noqa: F401  (sets the XLA CPU flag before JAX starts)

__version__ = "0.1.0"
