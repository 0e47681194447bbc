"""heisd-jax: hybrid speculative decoding for VLA policies, evaluated in batched MJX envs.

The decode API (docs/decode_api.md), importable from here without the simulator:
    Observation, VLAConfig, check_observation, decode_action, SpecConfig, load_policy,
    load_drafter, ActionTokenizer, expand_target, expand_drafter (a 7B VLA's costs: docs/scale.md),
    TargetModel, VLATarget (the interface a decoder calls a target through)

Layers, arrows one way (tests/test_layers.py pins them):
- the decode core, the modules of this package, which import nothing of the simulator: the
  models (`vla`, `drafter`, `tokenizer`, `observation`, `scale`, `checkpoint`), the
  target-model interface (`target_model`), the decoders and their rules (`spec_decode`,
  `hybrid`, `acceptance`, `retrieval`, `kinematics`, `budget`, `cost_model`) and the
  utilities (`sharding`, `timing`, `results_io`, `cache_dirs`, `rounded_products`, `xla_options`);
- `envs`, the simulation, which imports nothing of `heisd_jax`;
- `heisd_jax.harness` above both: the methods, the evaluator, replay, training and the
  offline builders;
- `experiments/`, the entry points, on top.
Names resolve on first use, so `import heisd_jax` itself imports nothing heavy and has no
side effects (the env package, `envs`, sets its own XLA flags when imported).
"""

import importlib as _importlib

__version__ = "0.1.0"

_EXPORTS = {
    "Observation": "heisd_jax.observation",
    "VLAConfig": "heisd_jax.vla",
    "check_observation": "heisd_jax.vla",
    "decode_action": "heisd_jax.spec_decode",
    "SpecConfig": "heisd_jax.spec_decode",
    "load_policy": "heisd_jax.checkpoint",
    "load_drafter": "heisd_jax.checkpoint",
    "ActionTokenizer": "heisd_jax.tokenizer",
    "expand_target": "heisd_jax.scale",
    "expand_drafter": "heisd_jax.scale",
    "TargetModel": "heisd_jax.target_model",
    "VLATarget": "heisd_jax.target_model",
}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(_importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'heisd_jax' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
