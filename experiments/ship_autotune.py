"""Makes the XLA autotuning results shipped beside the checkpoints (`checkpoints/xla_autotune.pbtxt`).

  python -m experiments.ship_autotune --methods=ar,expert,heisd --suites=all --episodes=50 [--num_envs=N] [--tail_envs=N] [--extend]

Compiles each method's evaluation rollout (`experiments.evaluate --compile_only`, one child
process each, a fresh compilation cache so nothing is skipped), every child loading the
results so far and dumping them with its own added (XLA's `--xla_gpu_load_autotune_results_from`
and `--xla_gpu_dump_autotune_results_to`). The file and its record (`.json` beside it: the
jax/jaxlib/plugin versions, the GPU, the commands, commit and date) are written only when
every compile succeeded, replacing the old pair. `import envs` loads the file on a GPU when the
installed versions are the recorded ones (envs/_xla.py). Run it on the GPU the results are for;
`--extend` keeps the entries already shipped (another GPU model's, or other batch sizes'): XLA
keys each entry by GPU model, so one file serves every model it holds entries for, and the
record lists each program with the GPU it was tuned on.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

from absl import app, flags

from envs import _xla
from heisd_jax import results_io
from heisd_jax.harness import methods
from experiments import cli

FLAGS = flags.FLAGS
flags.DEFINE_list("methods", ["ar", "expert", "heisd"], f"Methods whose rollouts to compile, of {sorted(methods.METHODS)}.")
flags.DEFINE_string("suites", "all", "As experiments.evaluate's --suites.")
flags.DEFINE_integer("episodes", 50, "As experiments.evaluate's --episodes.")
flags.DEFINE_integer("num_envs", 0, "As experiments.evaluate's --num_envs (the programs' batch size; 0: its default).",
                     lower_bound=0)
cli.define_tail_flag()  # a tail's programs are compiled (and autotuned) beside the head's
flags.DEFINE_bool("extend", False, "Start from the shipped entries (another GPU's, other batch sizes') instead of none.")
flags.DEFINE_string("out", str(_xla.SHIPPED_AUTOTUNE), "The results file (XLA text proto); its record is OUT with .json.")

def main(argv):
    del argv
    unknown = [m for m in FLAGS.methods if m not in methods.METHODS]
    if unknown or not FLAGS.methods:
        raise app.UsageError(f"--methods: unknown {unknown or 'none given'}; choose from {sorted(methods.METHODS)}")
    out = Path(FLAGS.out)
    if out.suffix != ".pbtxt":
        raise app.UsageError(f"--out must end in .pbtxt (XLA reads the text format by its suffix), got {out}")
    if FLAGS.extend and not out.is_file():
        raise app.UsageError(f"--extend: no results at {out} to extend")
    if not _xla.gpu_possible():
        raise app.UsageError("XLA autotunes only on a GPU: no CUDA plugin installed (jax-cuda*) or JAX_PLATFORMS "
                             f"excludes it ({os.environ.get('JAX_PLATFORMS') or 'unset'}); run this on the GPU the "
                             "results are for")
    common = [f"--suites={FLAGS.suites}", f"--episodes={FLAGS.episodes}", f"--num_envs={FLAGS.num_envs}",
              *([f"--tail_envs={FLAGS.tail_envs}"] if FLAGS.tail_envs else []), "--compile_only"]
    commands = []
    with tempfile.TemporaryDirectory(prefix="ship_autotune_") as tmp:
        load = str(out) if FLAGS.extend else ""
        for i, m in enumerate(FLAGS.methods):
            dump = str(Path(tmp) / f"results_{i}.pbtxt")
            cmd = [sys.executable, "-m", "experiments.evaluate", f"--method={m}", *common,
                   f"--compilation_cache={Path(tmp) / f'cache_{i}'}"]
            env = dict(os.environ, XLA_FLAGS=_xla.with_autotune_files(load, dump, os.environ.get("XLA_FLAGS", "")))
            print(f"{m}: compiling ({' '.join(cmd[1:])})", flush=True)
            r = subprocess.run(cmd, env=env)
            if r.returncode != 0 or not Path(dump).is_file():
                sys.exit(f"{m}: the compile failed (exit {r.returncode}) or wrote no results (XLA autotunes, and "
                         f"writes them, only on a GPU); {out} is unchanged")
            load = dump
            commands.append(f"python -m experiments.evaluate --method={m} {' '.join(common)}")
        text = Path(load).read_text()
        entries = sum(line.startswith("entries {") for line in text.splitlines())
        made = results_io.provenance(cli.command_line())  # the device: JAX starts here, once the children are done
        programs = [{"device": made["device"], "command": c} for c in commands]
        if FLAGS.extend and out.with_suffix(".json").is_file():  # the programs of the entries kept
            programs = [p for p in _xla.record_programs(json.loads(out.with_suffix(".json").read_text()))
                        if p not in programs] + programs
        record = {"versions": _xla.jax_versions(), "devices": sorted({p["device"] for p in programs}),
                  "entries": entries, "programs": programs, "extended": FLAGS.extend, "command": made["command"],
                  "commit": made["commit"], "date": made["date"]}
        out.parent.mkdir(parents=True, exist_ok=True)
        staged = out.with_name(f".{out.name}.tmp-{os.getpid()}")
        shutil.copyfile(load, staged)
        os.replace(staged, out)
        results_io.write_json_atomic(out.with_suffix(".json"), record)
    print(f"{entries} autotuning results for {', '.join(record['devices'])} ({record['versions']}): {out}")


if __name__ == "__main__":
    cli.run(main)
