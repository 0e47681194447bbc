"""One-off analyses behind figures in docs/ (physics agreement, draft sources, datastore
and boundary studies, action repeats, ...): run as `python -m experiments.studies.NAME`.
The entry points a user runs day to day (evaluate, sweep, build_target, the benchmarks,
profile) are in `experiments/` itself."""
