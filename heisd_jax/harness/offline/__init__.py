"""The offline builders: what is computed once, before decoding, and loaded by the methods.

Each runs only when its command is given; a method loads the artifact or fails naming the
command (it never builds one behind a user's back).

- Retrieval datastore: `heisd_jax.harness.offline.datastore`.
  Command: `python -m experiments.build_datastore --demos=DIR --out=DIR` (--values=target,
  --stride, --holdout). Artifact: DIR/datastore.npz (float16 keys, uint8 bins, task ids) and
  DIR/meta.json (key spec, tokenizer, target fingerprint, held-out episodes, the kinematic
  metric's feature scales). Loaded by `heisd_jax.retrieval.load` (from
  `heisd_jax.harness.methods.make_policy` for `retrieval` and `heisd`); the scales by
  `heisd_jax.harness.methods.load_calibration`.
- Boundary calibration: `heisd_jax.harness.offline.boundary`.
  Command: `python -m experiments.calibrate_boundary --demos=DIR --datastore=DIR`.
  Artifact: DIR/boundary.json in the datastore (tau_on, tau_off, min_dwell, skip_eps and the
  per-metric-bin table) and boundary.png. Loaded by `heisd_jax.harness.methods.load_calibration`.
- Decode-cost table for `budget=auto`: `heisd_jax.cost_model` (kept beside the budget that
  reads it). Command: `--calibrate_costs` on `experiments.evaluate`, `sweep`,
  `bench_methods`, `profile` or `timeline` (measured on the device in use, at the batch
  size in use). Artifact: `costs_<key digest>.json` in the cost cache (`--cost_cache`,
  default `~/.cache/heisd_jax/costs` or `$HEISD_CACHE/costs`). Loaded by
  `heisd_jax.cost_model.load_cached` (through `load_or_calibrate`, from
  `heisd_jax.harness.methods.make_policy`).

`heisd_jax.retrieval` (the run-time half: keys, query, load) imports none of these.
"""
