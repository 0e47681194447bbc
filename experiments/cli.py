"""How every entry point starts: absl flags, and a user's mistake answered in one line.

`run(main)` replaces `absl.app.run(main)`. A flag that does not parse or fails its validator,
and an `app.UsageError` raised by `main` while it checks its inputs (before anything
expensive starts), end the program with one line on stderr naming the problem and exit
status 2: no traceback, no usage text (`--helpshort` still prints the flags).

Every entry point also gets `--compilation_cache=DIR`: JAX's persistent compilation cache,
on by default in the user's cache directory, so a rerun loads its compiled MJX rollouts
from disk instead of compiling them again ('' turns it off); and the flags that join several
processes (hosts) into one JAX program (`--distributed`, `--coordinator_address`,
`--num_processes`, `--process_id`; docs/evaluator.md, "Several hosts").
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
import shlex
import signal
import sys
from typing import Callable, NoReturn

from absl import app, flags

from heisd_jax import results_io
from heisd_jax.cache_dirs import cache_root

USAGE_EXIT = 2
# Programs that compile faster than this are not worth a file each (most of a warm start's
# remaining compile time is tracing, which no cache skips); MJX rollouts take seconds to minutes.
MIN_COMPILE_SECONDS = 0.2


def default_compilation_cache() -> str:
    """$JAX_COMPILATION_CACHE_DIR if set (JAX's own variable; gpu_job.sh and build_target set it),
    else jax_compilation_cache/ under `cache_root()`."""
    return os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(cache_root() / "jax_compilation_cache")


def setup_compilation_cache(path: str | os.PathLike | None) -> str | None:
    """Points JAX's persistent compilation cache at `path` (created if missing); '' or None turns
    it off. Call before compiling what should be cached. Returns the directory in use, or None
    (off, or the directory cannot be created: then a warning, and everything still compiles)."""
    import jax  # noqa: PLC0415  (entry points that never compile need not import it)
    from jax.experimental.compilation_cache import compilation_cache  # noqa: PLC0415

    path = str(Path(path).expanduser()) if path else None
    if path:
        try:
            Path(path).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            sys.stderr.write(f"warning: compilation cache off: cannot create {path} ({e})\n")
            path = None
    jax.config.update("jax_compilation_cache_dir", path)
    if path:
        if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
            jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
        if "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES" not in os.environ:
            jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # any size
    # JAX decides once per process, at its first compile, whether the cache is used: start over
    # (quietly: under absl, JAX's INFO line about it would reach stderr).
    jax_logger = logging.getLogger("jax._src.compilation_cache")
    level = jax_logger.level
    jax_logger.setLevel(logging.WARNING)
    try:
        compilation_cache.reset_cache()
    finally:
        jax_logger.setLevel(level)
    return path


def _prog() -> str:
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None and spec.name:
        return f"python -m {spec.name}"
    return os.path.basename(sys.argv[0]) if sys.argv else "heisd-jax"


def command_line() -> str:
    """This process's command as a user would type it again (`python -m MODULE --flag=...`,
    after `XLA_FLAGS=...` where the user set them), for the results files that record what made
    them."""
    from envs import _xla  # noqa: PLC0415

    env = [f"XLA_FLAGS={shlex.quote(_xla.USER_FLAGS)}"] if _xla.USER_FLAGS else []
    return " ".join([*env, _prog(), *(shlex.quote(a) for a in sys.argv[1:])])


def fail(message: str) -> NoReturn:
    """Ends the program with one error line (the problem and the valid choices)."""
    first, *rest = str(message).strip().splitlines() or ["invalid input"]
    text = " ".join([first, *(line.strip() for line in rest)])
    sys.stderr.write(f"{_prog()}: error: {text}\n")
    sys.exit(USAGE_EXIT)


def _parse_flags(argv: list[str]) -> list[str]:
    try:
        return flags.FLAGS(argv)
    except flags.Error as e:
        fail(f"{e} (--helpshort lists the flags)")


def setup_distributed(coordinator_address: str | None = None, num_processes: int | None = None,
                      process_id: int | None = None) -> None:
    """`jax.distributed.initialize`: joins this process to the others of one multi-host run, so
    `jax.devices()` lists every process's devices. Arguments left None are read from the
    cluster (SLURM, Open MPI, ...) or, for the address, $JAX_COORDINATOR_ADDRESS. Must run
    before anything touches a device."""
    import jax  # noqa: PLC0415

    jax.distributed.initialize(coordinator_address=coordinator_address or None, num_processes=num_processes,
                               process_id=process_id)


flags.DEFINE_string("compilation_cache", default_compilation_cache(),
                    "JAX's persistent compilation cache directory (compiled programs reused across runs); '' = off.")
flags.DEFINE_bool("distributed", False, "Several processes (hosts) run one program: jax.distributed.initialize() "
                  "before anything starts, the cluster read from SLURM/Open MPI or from the three flags below.")
flags.DEFINE_string("coordinator_address", None, "--distributed: HOST:PORT of process 0 (default: from the cluster, "
                    "or $JAX_COORDINATOR_ADDRESS).")
flags.DEFINE_integer("num_processes", None, "--distributed: number of processes (default: from the cluster).",
                     lower_bound=1)
flags.DEFINE_integer("process_id", None, "--distributed: this process's index, 0..num_processes-1 (default: "
                     "from the cluster).", lower_bound=0)


def run(main: Callable[[list[str]], object]) -> None:
    """`absl.app.run(main)`, with bad flags and `app.UsageError` reported in one line; before
    `main` starts, this process joins a multi-host run (--distributed and co.) and the
    compilation cache of --compilation_cache is set up."""

    def checked_main(argv: list[str]):
        f = flags.FLAGS
        if f.distributed or f.coordinator_address or f.num_processes is not None or f.process_id is not None:
            setup_distributed(f.coordinator_address, f.num_processes, f.process_id)
        setup_compilation_cache(f.compilation_cache)
        try:
            return main(argv)
        except app.UsageError as e:
            fail(str(e))

    app.run(checked_main, flags_parser=_parse_flags)


class StopOnSignals:
    """A long run's way out that keeps its work: the first SIGTERM (`timeout`, a scheduler, a
    lease's end) or SIGINT (Ctrl-C) only sets a flag, which the run reads between rounds
    (`StopOnSignals.__call__`, an `evaluator.evaluate` `stop`), saving what has ended before it
    exits; the handlers then return to the defaults, so a second signal ends the process at
    once (during a compile, which no round interrupts, that is the way out). `exit_code`:
    the shell's 128 + the signal's number."""

    def __init__(self):
        self.signum = None
        self._before = {s: signal.signal(s, self._handle) for s in (signal.SIGTERM, signal.SIGINT)}

    def _handle(self, signum, frame) -> None:
        del frame
        self.signum = signum
        for s, handler in self._before.items():
            signal.signal(s, handler)
        print(f"\n{signal.Signals(signum).name}: stopping after this round, its ended episodes saved "
              "(again to stop now)", file=sys.stderr, flush=True)

    def __call__(self) -> bool:
        return self.signum is not None

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum or 0)

    def exit(self) -> None:
        """Ends the process now with `exit_code`, its output flushed, once the run's work is
        written: without waiting for threads still compiling (a queue's tail program compiles
        in the background, minutes at 7B, and the interpreter's exit would join it, outlasting
        the grace a scheduler gives between SIGTERM and SIGKILL)."""
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(self.exit_code)


def task_list(suites: str, names: list[str] | None = None) -> list:
    """`envs.tasks.get_tasks(suites, names or None)`, an unknown suite or task raised as the
    `app.UsageError` that names the valid ones (call it from `main` before anything expensive)."""
    from envs import tasks as tasks_lib  # noqa: PLC0415

    try:
        return tasks_lib.get_tasks(suites, names or None)
    except ValueError as e:
        raise app.UsageError(str(e)) from e


def load_target(path: str):
    """(params, cfg) of the target checkpoint at path, with the instruction vocabulary's check; a
    missing or unreadable checkpoint raised as the `app.UsageError` that names it."""
    from envs import language  # noqa: PLC0415
    from heisd_jax import checkpoint  # noqa: PLC0415

    try:
        params, cfg, _, _ = checkpoint.load_policy(path, text_vocab=language.VOCAB)
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    return params, cfg


def failure_weights(path: str) -> list[str]:
    """`envs.tasks.failure_weights` of a policy's per-task success rates, read from an
    evaluation's results JSON (experiments.evaluate --out) or from a DAgger dataset
    (collect_demos --policy: the success of the episodes that policy drove); ValueError
    naming the path when it is neither."""
    from envs import demos, tasks as tasks_lib  # noqa: PLC0415  (entry points that weigh nothing need not import envs)

    if Path(path).is_dir():
        try:
            ds = demos.DemoDataset(path)
        except (OSError, ValueError) as e:
            raise ValueError(f"weights from {path}: not a complete dataset: {e}") from None
        if ds.meta.get("policy", "expert") == "expert":
            raise ValueError(f"weights from {path}: an expert dataset (its episodes are the successful ones only); "
                             f"give a DAgger dataset (collect_demos --policy) or an evaluation's results JSON")
        runs: dict[str, list[bool]] = {}
        for r in ds.episodes:
            runs.setdefault(r["task"], []).append(bool(r["success"]))
        rates = {name: sum(v) / len(v) for name, v in runs.items()}
    else:
        try:
            summary = results_io.read_json(path)["summary"]["tasks"]
            rates = {name: float(row["success_rate"]) for name, row in summary.items()}
        except (ValueError, KeyError, TypeError) as e:
            raise ValueError(f"weights from {path}: neither a DAgger dataset nor an evaluation's results JSON with "
                             f"per-task success (summary.tasks.*.success_rate): {e}") from None
    return tasks_lib.failure_weights(rates)


def load_eval_results(path: str) -> dict:
    """An `experiments.evaluate` results file (plain or gzipped JSON) with its per-episode and
    per-task results; ValueError naming the path when it is not one."""
    d = results_io.read_json(path)
    try:
        d["episodes"], d["summary"]["tasks"]  # noqa: B018  (an evaluate result has both)
    except (KeyError, TypeError) as e:
        raise ValueError(f"{path}: not an experiments.evaluate result ({type(e).__name__}: {e})") from e
    return d


def positive_int_list(flag_name: str) -> None:
    """Validates a DEFINE_list flag as comma-separated positive integers when flags parse."""
    flags.register_validator(
        flag_name, lambda values: all(str(v).strip().isdigit() and int(v) > 0 for v in values),
        message="expected comma-separated positive integers")


def existing_dir(flag_name: str, what: str) -> None:
    """Validates a path flag when flags parse: empty (none) or an existing directory."""

    def check(value: str) -> bool:
        if value and not Path(value).is_dir():
            raise flags.ValidationError(f"no {what} there")
        return True

    flags.register_validator(flag_name, check)


def define_cost_flags() -> None:
    """--cost_cache and --calibrate_costs, for the entry points that build methods with
    budget=auto; `cost_kwargs` passes them on to `methods.make_policy`."""
    if "calibrate_costs" in flags.FLAGS:
        return
    from heisd_jax import cost_model  # noqa: PLC0415

    flags.DEFINE_string("cost_cache", str(cost_model.DEFAULT_CACHE),
                        "budget=auto: directory of measured cost tables (per device, model and batch size); '' = none.")
    flags.DEFINE_bool("calibrate_costs", False, "budget=auto: where no decode-cost table is cached for this device, "
                      "model, settings and batch size, measure it now (about a minute for the shipped target, several for a 7B expansion; then cached) instead of failing.")


def method_label(name: str, settings: dict) -> str:
    """NAME or NAME:key=value,... (the settings in the order given), as --methods spells a method."""
    return name + (":" + ",".join(f"{k}={v}" for k, v in settings.items()) if settings else "")


def check_methods(method_list: list[tuple[str, dict]], batch_sizes, checkpoint=None, datastore=None) -> None:
    """`app.UsageError`, before anything runs, naming a method whose draft trees or candidates
    do not fit the target's KV cache (`methods.check_fits`), and every method and batch size
    (rows per device) whose budget=auto would find no decode-cost table in --cost_cache
    (`methods.missing_cost_tables`; unless --calibrate_costs measures them)."""
    from heisd_jax.harness import methods  # noqa: PLC0415

    for n, s in method_list:
        try:
            methods.check_fits(n, checkpoint=checkpoint, **s)
        except (ValueError, FileNotFoundError) as e:
            raise app.UsageError(f"{method_label(n, s)}: {e}") from e
    f = flags.FLAGS
    if f.calibrate_costs:
        return
    try:
        missing = {method_label(n, s): methods.missing_cost_tables(n, batch_sizes, checkpoint=checkpoint,
                                                                      datastore=datastore,
                                                                      cost_cache=cost_kwargs()["cost_cache"], **s)
                   for n, s in method_list}
    except (ValueError, FileNotFoundError) as e:
        raise app.UsageError(str(e)) from e
    missing = {k: v for k, v in missing.items() if v}
    if missing:
        where = f.cost_cache or "(no --cost_cache)"
        raise app.UsageError(
            f"budget=auto needs a decode-cost table per device, model, settings and batch size, and {where} has none "
            f"for {'; '.join(f'{k} at batch {v}' for k, v in missing.items())}: add --calibrate_costs to measure them "
            f"first (cached for later runs), pass the --cost_cache that holds them, or use budget=fixed")


def cost_kwargs() -> dict:
    """`methods.make_policy`'s cost-table arguments from the flags `define_cost_flags` made."""
    return {"cost_cache": flags.FLAGS.cost_cache or None, "calibrate_costs": flags.FLAGS.calibrate_costs}


def define_tail_flag() -> None:
    """--tail_envs (`EvalConfig.tail_envs`), for the entry points that run evaluations."""
    from heisd_jax.harness import evaluator  # noqa: PLC0415

    flags.DEFINE_integer("tail_envs", evaluator.EvalConfig.tail_envs,
                         "With refilled slots: once no episode is pending and at most this many envs still run, they "
                         "go on in a batch of this size, so the queue's last, longest episodes do not pay a full "
                         "batch's step (a second copy of the step in the program: a longer compile; faster on a warm "
                         "compilation cache, docs/evaluator.md). 0: off.")


def define_physics_flag() -> None:
    """--physics (`envs.physics.PhysicsConfig` as 'field=value,...'), checked when flags parse."""
    from envs import physics  # noqa: PLC0415

    fields = ", ".join(f.name for f in dataclasses.fields(physics.PhysicsConfig))
    flags.DEFINE_string("physics", "", f"The simulator's settings that differ from the defaults, as 'field=value,...' "
                        f"(e.g. 'max_contacts=0' for every contact, 'clamp_aware_implicit=true'); fields: {fields} "
                        f"(envs/physics.py). Recorded in the results.")

    def check(value: str) -> bool:
        try:
            physics.parse(value)
        except ValueError as e:
            raise flags.ValidationError(str(e)) from None
        return True
    flags.register_validator("physics", check)


def physics_config():
    """The `envs.physics.PhysicsConfig` of --physics."""
    from envs import physics  # noqa: PLC0415

    return physics.parse(flags.FLAGS.physics)


def define_store_flag() -> None:
    """--executable_store, for the entry points that compile rollouts; `executable_store` makes
    the store it names."""
    flags.DEFINE_string("executable_store", str(cache_root() / "executables"),
                        "Directory of compiled rollouts keyed by the code, settings, checkpoints, versions and devices "
                        "that make them: a warm run loads its program without tracing it (docs/evaluator.md). "
                        "'' = off.")


def executable_store(method: str, settings: dict):
    """The store of --executable_store for `method`'s programs at `settings` (its flags), named
    also by digests of the files it loads (--checkpoint, --drafter, --datastore: a retrained
    checkpoint at the same path is another program), except those whose contents reach the
    programs only as inputs and keyed meta (`Method.shares_programs`); None when the flag is
    empty."""
    from heisd_jax.harness import executable_store as store_lib, methods  # noqa: PLC0415

    if not flags.FLAGS.executable_store:
        return None
    m = methods.get(method)
    files = {name: store_lib.file_digest(getattr(flags.FLAGS, name)) for name in m.loads if name not in m.shares_programs}
    return store_lib.ExecutableStore(flags.FLAGS.executable_store,
                                     {"method": method, "settings": settings, "files": files})


def contents(names) -> dict[str, str | None]:
    """What each of the path flags `names` (--checkpoint, --drafter, --datastore) holds: a
    short digest of its files, None where nothing is there (loading it fails later with its
    own error). Recorded in a results file's settings, so a run over other files at the same
    paths (a target installed since) never resumes it as if done."""
    from heisd_jax.harness import executable_store as store_lib  # noqa: PLC0415

    out = {}
    for name in names:
        path = Path(getattr(flags.FLAGS, name))
        out[name] = store_lib.file_digest(path)[:16] if path.exists() else None
    return out


def config_digest(method: str, given: dict) -> str:
    """A short digest of every setting method `method` runs with under the settings `given`
    (its defaults filled in). Recorded beside the given settings, so results made under
    another default (a release that changed it) are never resumed as if they were this one's."""
    import hashlib  # noqa: PLC0415
    import json  # noqa: PLC0415

    from heisd_jax.harness import methods  # noqa: PLC0415

    resolved = methods.settings_of(method, methods.config(method, given))
    return hashlib.sha256(json.dumps(resolved, sort_keys=True, default=str).encode()).hexdigest()[:16]


PATH_FLAGS = {  # flag -> (what it names, its help line); defaults: the shipped artifacts
    "checkpoint": ("policy checkpoint", "Target VLA checkpoint (default: the shipped one)."),
    "drafter": ("drafter checkpoint", "Drafter checkpoint, trained on the target (default: the shipped one)."),
    "datastore": ("datastore", "Retrieval datastore with its boundary calibration (default: the shipped one)."),
}


def define_paths(*names: str) -> None:
    """--checkpoint / --drafter / --datastore, defaulting to the shipped artifacts and checked
    when flags parse (an existing directory)."""
    from heisd_jax.harness import vla_policy  # noqa: PLC0415  (after the entry point's `import envs`)

    defaults = {"checkpoint": vla_policy.DEFAULT_CHECKPOINT, "drafter": vla_policy.DEFAULT_DRAFTER,
                "datastore": vla_policy.DEFAULT_DATASTORE}
    for name in names:
        what, text = PATH_FLAGS[name]
        flags.DEFINE_string(name, str(defaults[name]), text)
        existing_dir(name, what)


def paths(*names: str) -> dict:
    """The path flags `define_paths` made, as `methods.load_hybrid` takes them."""
    return {name: Path(getattr(flags.FLAGS, name)) for name in names}
