"""The harness: what runs the decode core in simulation, above both it and `envs`.

- `methods`: each decoding method as one record (its settings, defaults and builder);
- `vla_policy`: a method's decoder as an env policy (observations from env states);
- `evaluator`: batched closed-loop evaluation over MJX envs, sharded over devices, with
  `executable_store` keeping its compiled programs across processes;
- `replay`: recorded closed-loop states replayed through a method (decode speed alone);
- `data` and `training`: demonstration tables and the target's and drafter's training steps;
- `offline/`: the builders of what a method loads (the retrieval datastore, the boundary
  calibration).

The decode core (`heisd_jax.vla`, `spec_decode`, `hybrid`, ...) imports nothing of this
package, and `envs` imports nothing of `heisd_jax` (tests/test_layers.py).
"""
