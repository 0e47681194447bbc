"""Rebuilds the whole target stack from nothing, resumably: expert demonstrations -> a first
VLA trained on them -> DAgger rounds (the VLA drives, the expert labels, the aggregate is
trained on) -> the closed-loop evaluation -> the drafter -> the retrieval datastore -> the
boundary calibration; optionally installs the results as the shipped checkpoints.

  python -m experiments.build_target --work=runs/target             # on one GPU, ~30 minutes
  python -m experiments.build_target --work=runs/target --install   # ... and copy to checkpoints/

Each stage is one of the project's own commands (collect_demos, train, evaluate,
build_datastore, calibrate_boundary), run as a subprocess with its output in
--work/logs/<stage>.log. A stage is done when its output exists (datasets and checkpoints
are published atomically by those commands), so rerunning the same command after an
interruption skips what is done and resumes the stage that was cut off (training resumes
from its last orbax checkpoint); a stage whose output is gone runs again only where a stage
still to run reads it, so a build moved to another machine with its newest policy and
evaluation resumes after them where nothing after them reads an earlier dataset.
--fresh_round adds one round after the evaluation on fresh, failure-weighted data, drawn
--fresh_weight times as often as the aggregate's (docs/target.md). --work/build.json records
the settings (a rerun with other settings is refused) and, per stage, its wall time and the
figures it printed (DAgger success of the policy that drove, held-out token accuracy and
decisiveness (the share of tokens whose greedy bin has probability > 0.5), evaluation
success, a collection's time split).
A persistent JAX compilation cache under --work makes recompiles of a resumed or repeated
stage cheap.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from absl import app, flags
from experiments import cli
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

FLAGS = flags.FLAGS
flags.DEFINE_string("work", "runs/target", "Working directory (datasets, runs, logs, build.json).")
flags.DEFINE_integer("demo_episodes", 40, "Expert episodes attempted per task.")
flags.DEFINE_float("action_noise", 0.15, "Noise on the expert's executed actions in demonstrations (labels clean).")
flags.DEFINE_integer("rounds", 6, "DAgger rounds after the first (behaviour-cloned) policy.")
flags.DEFINE_float("expert_rot_gain", None, "The labelling expert's rotation gain in every collection "
                   "(collect_demos --expert_rot_gain; unset: the expert's own, envs.expert.ExpertConfig.rot_gain): "
                   "lower keeps its yaw labels proportional over more of a turn (docs/target.md).")
flags.DEFINE_integer("dagger_episodes", 25, "Episodes per task in each DAgger round.")
flags.DEFINE_list("suite_weights", ["spatial:2", "long:2"], "SUITE:N or TASK:N,...: the tasks of these suites, or "
                  "these tasks, get N times the episodes per task in the demonstrations and every DAgger round; a "
                  "task's own weight overrides its suite's; others 1.")
flags.DEFINE_string("weights_from", "", "An evaluation's results JSON (experiments.evaluate --out): each task it "
                    "holds gets episodes in proportion to how often that policy failed it (envs.tasks.failure_weights, "
                    "up to 4x); a task named in --suite_weights keeps the weight given there.")
flags.DEFINE_bool("adapt_weights", False, "Follow where the policy fails: from the second DAgger round on, each "
                  "round's collection shares its episodes out in proportion to how often the previous round's policy "
                  "failed each task there (collect_demos --weights_from --keep_total: up to 4x, on top of "
                  "--suite_weights; each time limit's total stays what --dagger_episodes and --suite_weights give, so "
                  "every round runs one compiled program), and each round whose policy drove alone (beta 0) "
                  "fine-tunes on the aggregate drawn by that round's failures (train --weights_from: the policy it "
                  "fine-tunes is the one that failed them).")
flags.DEFINE_bool("fresh_round", False, "After the evaluation, one DAgger round more on fresh data: the final "
                  "policy drives alone (beta 0) and the expert demonstrates afresh, both collections shared out by that "
                  "evaluation's failures (collect_demos --weights_from=eval_ar.json --keep_total: up to 4x, on top of "
                  "--suite_weights, at the totals of the build's own collections, so their programs are reused), the "
                  "policy fine-tuned on them as --fresh_weight says (--dagger_steps, the last label std) and evaluated "
                  "again (eval_ar_fresh.json); it is the build's final policy. Needs the evaluation (not in --skip).")
flags.DEFINE_integer("fresh_weight", 4, "With --fresh_round: the fresh round fine-tunes on the whole aggregate and "
                     "the two fresh datasets, each fresh step drawn this many times as often as an earlier round's "
                     "(train --demo_weights; at the default sizes 4 gives the fresh data ~46% of the draws), so the "
                     "round adds where the policy fails without forgetting the rest. 0: on the two fresh datasets "
                     "alone; its inputs are then only the last policy and eval_ar.json, which a lost machine's last "
                     "poll brings back, so a build resumed elsewhere from those two runs only the fresh stages.")
flags.DEFINE_list("beta", ["0.5", "0"], "DAgger: probability of executing the expert's action per step, one value per "
                  "round (the last one repeats), e.g. 0.5,0.25,0: the first rounds stay near the expert's paths, "
                  "the last visits the policy's own states.")
flags.DEFINE_integer("steps", 6000, "Optimizer steps of the first policy (with --start: of training it further on "
                     "the demonstrations; 0: use it as it is).")
flags.DEFINE_integer("dagger_steps", 4500, "Optimizer steps of each DAgger round's fine-tuning (the aggregate "
                     "grows each round: at 4,500 x 256 the fourth round sees ~0.9 epochs of it).")
flags.DEFINE_float("lr", 5e-4, "Peak learning rate (fine-tuning rounds use half).")
flags.DEFINE_integer("batch_size", 256, "Training minibatch.")
flags.DEFINE_list("label_sigma_bins", ["2", "2", "0.6"], "Ordinal label smoothing (Gaussian targets of this std in bins; 0: "
                  "one-hot), one value per policy trained: the first, then each DAgger round's fine-tuning (the last "
                  "value repeats). The default gives wide labels to the first policy and the first round and sharp "
                  "ones after, as the shipped target was made (with --start and --steps=0 the first value goes unused). Smaller makes the greedy bin stand out more (a more confident target); 0.6, the "
                  "shipped target's last, lets its tokens survive bf16 rounding (docs/target.md).")
flags.DEFINE_enum("param_dtype", "bfloat16", ["float32", "bfloat16"], "The dtype every policy of the build is stored "
                  "in (train --export_param_dtype); a policy runs in its stored dtype, so bfloat16 makes bf16 the "
                  "precision of the DAgger rollouts, the evaluation and the installed target. Training always keeps "
                  "float32 master weights and computes in bfloat16.")
flags.DEFINE_integer("d_model", 256, "Decoder width.")
flags.DEFINE_integer("n_layers", 8, "Decoder layers.")
flags.DEFINE_integer("drafter_steps", 4000, "Drafter optimizer steps.")
flags.DEFINE_integer("seed", 0, "Every training stage's seed (initialisation and minibatch order).")
flags.DEFINE_bool("deterministic", True, "Every training, collection and evaluation stage compiled with deterministic "
                  "GPU reductions and convolutions (train, collect_demos and evaluate --deterministic), so that a seed "
                  "reproduces a stage's parameters, data and figures. Not a setting of the build's recipe: a build "
                  "resumes with either.")
flags.DEFINE_integer("train_devices", 0, "Local devices each training stage runs on, data parallel (0: all of them; "
                     "experiments.train --devices); --batch_size must be a multiple.")
flags.DEFINE_integer("rollout_episodes", 25, "Episodes per task in which the final target drives alone (beta 0, "
                     "~2 minutes on an H200): added to the drafter's training states, so it learns to predict the "
                     "target where the target itself goes, and with --datastore_source=rollouts the datastore's "
                     "contents; 0: none (the drafter sees the demonstrations and the DAgger rounds, the last of which "
                     "the previous policy drove alone). Skipped with the drafter unless the datastore needs them.")
flags.DEFINE_enum("datastore_source", "demos", ["demos", "rollouts"], "The retrieval datastore's episodes: the "
                  "expert demonstrations, or the final target's own rollouts (--rollout_episodes; build_datastore "
                  "--values=rollout: keyed and valued by what the target executed).")
flags.DEFINE_integer("num_envs", 1000, "Parallel envs for collection and evaluation.")
flags.DEFINE_integer("eval_episodes", 50, "Evaluation episodes per task (the fixed evaluation states).")
flags.DEFINE_string("suites", "all", "Suites to build on.")
flags.DEFINE_list("tasks", [], "Only these tasks (smoke tests).")
flags.DEFINE_list("skip", [], "Stages to skip: eval, drafter, datastore, calibration.")
flags.DEFINE_bool("dry_run", False, "Print the stages' commands (and which are done) without running any.")
flags.DEFINE_bool("install", False, "Copy the final target, drafter and datastore into checkpoints/ at the end.")
flags.DEFINE_integer("image_size", 64, "Camera resolution of each view.")
flags.DEFINE_string("start", "", "Start the DAgger rounds from this policy checkpoint instead of training a first "
                    "policy on the demonstrations (continuing an earlier build).")
cli.existing_dir("start", "policy checkpoint")

TIME = {"time": r"\ntime: ([^\n]*)"}  # a collection's, training's or evaluation's split of its seconds
SKIPPABLE = ("eval", "drafter", "datastore", "calibration")
ROOT = Path(__file__).resolve().parents[1]


@dataclasses.dataclass
class Stage:
    name: str
    args: list[str]  # python -m experiments.<module> ...
    output: Path  # what the stage writes
    figures: dict[str, str] = dataclasses.field(default_factory=dict)  # name -> regex on the stage's output
    expected_episodes: int = 0  # an evaluation: complete once its results hold this many episodes

    def done(self) -> bool:
        if not self.output.exists():
            return False
        if self.expected_episodes:  # evaluate writes its results file after every batch
            results = json.loads(self.output.read_text())["episodes"]
            return sum(len(v) for v in results.values()) >= self.expected_episodes
        if self.args[0] == "train":  # an orbax checkpoint directory: complete once its step is renamed in
            return (self.output / "0").is_dir()
        return True  # datasets, datastores and boundary files are published whole

    def reads(self, other: Stage) -> bool:
        """Whether this stage's command names `other`'s output among its flags' values."""
        return any(str(other.output) in arg.split("=", 1)[-1].split(",") for arg in self.args)


def to_run(stages: list[Stage]) -> list[bool]:
    """Which stages still run: each one not done whose output is still wanted, by a stage that
    still runs or, for a stage no other reads and that is no collection, as one of the build's
    results (a dataset is only ever some stage's input). A stage whose output is gone but whose
    every reader is done is not rerun: a build resumed on another machine from what a lost
    one's last poll brought back (build.json, the newest policy, the evaluation) runs only what
    comes after them, where it needs no earlier dataset."""
    run = [False] * len(stages)
    for i in reversed(range(len(stages))):
        if not stages[i].done():
            readers = [j for j in range(i + 1, len(stages)) if stages[j].reads(stages[i])]
            result = not readers and stages[i].args[0] != "collect_demos"
            run[i] = result or any(run[j] for j in readers)
    return run


def _policy(w: Path, r: int) -> Path:
    if r == 0 and FLAGS.start and not FLAGS.steps:
        return Path(FLAGS.start).absolute()
    return w / f"vla{r}"


def _final_round() -> int:
    """The round whose policy the build ends with (the fresh round's, where there is one)."""
    return FLAGS.rounds + int(FLAGS.fresh_round)


def _schedule(name: str, hi: float = float("inf")) -> list[float]:
    """The numbers of list flag `name`, each in [0, hi]; UsageError naming the flag otherwise."""
    text = ",".join(getattr(FLAGS, name))
    try:
        values = [float(v) for v in getattr(FLAGS, name)]
    except ValueError:
        raise app.UsageError(f"--{name}: expected comma-separated numbers, got {text}") from None
    if not values or not all(0 <= v <= hi for v in values):
        bound = f"in [0, {hi:g}]" if hi < float("inf") else ">= 0"
        raise app.UsageError(f"--{name}: each value must be {bound}, got {text}")
    return values


def _beta(r: int) -> float:
    """DAgger round r's (1-based) beta."""
    betas = _schedule("beta", 1.0)
    return betas[min(r, len(betas)) - 1]


def _sigma(r: int) -> float:
    """The label std of policy r's training (0: the first policy, r: DAgger round r's)."""
    sigmas = _schedule("label_sigma_bins")
    return sigmas[min(r, len(sigmas) - 1)]


def plan(w: Path) -> list[Stage]:
    """The stages, in order, for the current flags."""
    scope = [f"--suites={FLAGS.suites}"] + ([f"--tasks={','.join(FLAGS.tasks)}"] if FLAGS.tasks else [])
    # Suite weights shape the training data only; the evaluation runs every task's fixed states.
    collect = scope + ([f"--suite_weights={','.join(FLAGS.suite_weights)}"] if FLAGS.suite_weights else [])
    labels = [] if FLAGS.expert_rot_gain is None else [f"--expert_rot_gain={FLAGS.expert_rot_gain:g}"]  # every collection's
    determinism = [] if FLAGS.deterministic else ["--deterministic=false"]
    model = [f"--d_model={FLAGS.d_model}", f"--n_layers={FLAGS.n_layers}", f"--batch_size={FLAGS.batch_size}",
             f"--export_param_dtype={FLAGS.param_dtype}", "--image_shift=2", "--log_every=500", "--ckpt_every=1000",
             f"--devices={FLAGS.train_devices}", f"--seed={FLAGS.seed}", *determinism]
    acc = {"held_out_token_acc": r'"val_token_acc": (\[[^\]]*\])', "held_out_decisive": r'"val_decisive": (\[[^\]]*\])', **TIME}
    from envs import tasks as tasks_lib  # noqa: PLC0415

    n_tasks = len(tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None))

    def demonstrations(name: str, out: Path, *extra: str) -> Stage:
        return Stage(name, ["collect_demos", *collect, *labels, *extra, *determinism,
                            f"--episodes_per_task={FLAGS.demo_episodes}", f"--num_envs={FLAGS.num_envs}",
                            f"--action_noise={FLAGS.action_noise}", "--wrist", f"--image_size={FLAGS.image_size}",
                            f"--out={out}"], out, {"kept": r"kept (\d+/\d+)", **TIME})

    def dagger(r: int, beta: float, *extra: str) -> Stage:  # round r: policy r - 1 drives (the expert too, by beta)
        out = w / f"dagger{r}"
        return Stage(f"dagger{r}", ["collect_demos", *collect, *labels, *extra, *determinism,
                                    f"--policy={_policy(w, r - 1)}", f"--beta={beta}",
                                    f"--episodes_per_task={FLAGS.dagger_episodes}", f"--first_episode={100000 * r}",
                                    f"--num_envs={FLAGS.num_envs}", "--action_noise=0", f"--out={out}"], out,
                     {"policy_success": r"policy success ([\d.]+%)", "agreement": r"on ([\d.]+%) of", **TIME})

    def fine_tune(r: int, data: list[str], *extra: str) -> Stage:  # policy r from policy r - 1
        return Stage(f"train{r}", ["train", "--model=vla", f"--demos={','.join(data)}", f"--out={w / f'run{r}'}",
                                   f"--init={_policy(w, r - 1)}", f"--steps={FLAGS.dagger_steps}",
                                   f"--lr={FLAGS.lr / 2}", f"--warmup_steps={min(200, FLAGS.dagger_steps // 4)}", *model,
                                   f"--label_sigma_bins={_sigma(r):g}", *extra,
                                   f"--export={_policy(w, r)}"], _policy(w, r), acc)

    def evaluation(name: str, policy: Path, out: Path) -> Stage:
        return Stage(name, ["evaluate", "--method=ar", f"--checkpoint={policy}", *scope,
                            *(["--deterministic"] if FLAGS.deterministic else []),
                            f"--episodes={FLAGS.eval_episodes}", f"--num_envs={FLAGS.num_envs}", f"--out={out}"], out,
                     {**{f"success_{s}": rf"\n{s}\s+\d+\s+([\d.]+)" for s in ("spatial", "object", "goal", "long")}, **TIME},
                     expected_episodes=n_tasks * FLAGS.eval_episodes)

    stages = [demonstrations("demos", w / "demos"),
              Stage("train0", ["train", "--model=vla", f"--demos={w / 'demos'}", f"--out={w / 'run0'}",
                               f"--steps={FLAGS.steps}", f"--lr={FLAGS.lr}", f"--warmup_steps={min(300, FLAGS.steps // 4)}", *model,
                               f"--label_sigma_bins={_sigma(0):g}",
                               f"--export={_policy(w, 0)}"], _policy(w, 0), acc)]
    if FLAGS.start:  # round 0 is the given policy, trained on for --steps more (none: as it is)
        if FLAGS.steps:
            stages[-1].args += [f"--init={FLAGS.start}"]
        else:
            stages.pop()
    data = [str(w / "demos")]
    for r in range(1, FLAGS.rounds + 1):
        data.append(str(w / f"dagger{r}"))
        adapt = [f"--weights_from={w / f'dagger{r - 1}'}", "--keep_total"] if FLAGS.adapt_weights and r > 1 else []
        drawn = [f"--weights_from={w / f'dagger{r}'}"] if FLAGS.adapt_weights and _beta(r) == 0 else []
        stages += [dagger(r, _beta(r), *adapt), fine_tune(r, data, *drawn)]
    if "eval" not in FLAGS.skip:
        stages.append(evaluation("eval", _policy(w, FLAGS.rounds), w / "eval_ar.json"))
    if FLAGS.fresh_round:  # one round more, on fresh data weighted by that evaluation's failures
        r, weighed = FLAGS.rounds + 1, [f"--weights_from={w / 'eval_ar.json'}", "--keep_total"]
        fresh = [str(w / "fresh_demos"), str(w / f"dagger{r}")]
        drawn = ",".join(["1"] * len(data) + [str(FLAGS.fresh_weight)] * len(fresh))  # the aggregate's steps 1
        stages += [demonstrations("fresh_demos", w / "fresh_demos", *weighed, f"--first_episode={100000 * r + 50000}"),
                   dagger(r, 0.0, *weighed),
                   fine_tune(r, data + fresh, f"--demo_weights={drawn}") if FLAGS.fresh_weight else fine_tune(r, fresh),
                   evaluation("fresh_eval", _policy(w, r), w / "eval_ar_fresh.json")]
        data += fresh
    final = _policy(w, _final_round())
    rollouts = w / "target_rollouts"
    datastore_from_rollouts = FLAGS.datastore_source == "rollouts" and "datastore" not in FLAGS.skip
    if FLAGS.rollout_episodes and ("drafter" not in FLAGS.skip or datastore_from_rollouts):
        if "drafter" not in FLAGS.skip:
            data.append(str(rollouts))
        stages.append(Stage("target_rollouts", ["collect_demos", *scope, *labels, *determinism, f"--policy={final}",
                                                "--beta=0",
                                                f"--episodes_per_task={FLAGS.rollout_episodes}",
                                                f"--first_episode={100000 * (_final_round() + 1)}",
                                                f"--num_envs={FLAGS.num_envs}", "--action_noise=0", f"--out={rollouts}"],
                            rollouts, {"policy_success": r"policy success ([\d.]+%)", **TIME}))
    if "drafter" not in FLAGS.skip:
        stages.append(Stage("drafter", ["train", "--model=drafter", f"--target={final}", f"--demos={','.join(data)}",
                                        f"--out={w / 'drafter_run'}", f"--steps={FLAGS.drafter_steps}", *determinism,
                                        f"--batch_size={FLAGS.batch_size}", "--lr=1e-3", f"--warmup_steps={min(200, FLAGS.drafter_steps // 4)}",
                                        "--log_every=500", "--ckpt_every=1000", f"--devices={FLAGS.train_devices}", f"--seed={FLAGS.seed}",
                                        f"--export={w / 'drafter'}"],
                            w / "drafter", {"val_top1": r'"val_top1": (\[[^\]]*\])', **TIME}))
    source = rollouts if FLAGS.datastore_source == "rollouts" else w / "demos"
    if "datastore" not in FLAGS.skip:
        stages.append(Stage("datastore", ["build_datastore", f"--demos={source}", f"--checkpoint={final}",
                                          *(["--values=rollout"] if source == rollouts else []),
                                          f"--out={w / 'datastore'}"], w / "datastore"))
    if "calibration" not in FLAGS.skip and "datastore" not in FLAGS.skip and "drafter" not in FLAGS.skip:
        stages.append(Stage("calibration", ["calibrate_boundary", f"--demos={source}",
                                            f"--datastore={w / 'datastore'}", f"--checkpoint={final}",
                                            f"--drafter={w / 'drafter'}"], w / "datastore" / "boundary.json"))
    return stages


def local_device_count() -> int:
    """JAX's local devices, counted in a child process: a backend started in this driver would
    hold device memory that its stages (each a process of its own) need."""
    r = subprocess.run([sys.executable, "-c", "import jax; print(jax.local_device_count())"], capture_output=True,
                       text=True, timeout=300)
    if r.returncode:
        raise RuntimeError(f"counting JAX's local devices failed: {r.stderr.strip()[-2000:]}")
    return int(r.stdout.strip().splitlines()[-1])


def _settings() -> dict:
    keys = ("demo_episodes", "action_noise", "rounds", "dagger_episodes", "beta", "steps", "dagger_steps", "lr",
            "batch_size", "d_model", "n_layers", "drafter_steps", "rollout_episodes", "suites", "tasks",
            "image_size", "start")
    out = {k: getattr(FLAGS, k) for k in keys}
    out["beta"] = [_beta(r) for r in range(1, FLAGS.rounds + 1)]
    if FLAGS.suite_weights:  # recorded only when given, so builds made before the flag still resume
        out["suite_weights"] = list(FLAGS.suite_weights)
    if FLAGS.datastore_source != "demos":  # likewise
        out["datastore_source"] = FLAGS.datastore_source
    sigmas = [_sigma(r) for r in range(FLAGS.rounds + 1)]
    if set(sigmas) != {2.0}:  # likewise; one number where every policy has the same (as builds before the schedule)
        out["label_sigma_bins"] = sigmas[0] if len(set(sigmas)) == 1 else sigmas
    if FLAGS.seed:  # likewise
        out["seed"] = FLAGS.seed
    if FLAGS.adapt_weights:  # likewise
        out["adapt_weights"] = True
    if FLAGS.expert_rot_gain is not None:  # likewise
        out["expert_rot_gain"] = FLAGS.expert_rot_gain
    if FLAGS.fresh_round:  # likewise
        out["fresh_round"] = True
        if FLAGS.fresh_weight:  # likewise: a build with the fresh round on its data alone records none
            out["fresh_weight"] = FLAGS.fresh_weight
    if FLAGS.param_dtype != "float32":  # likewise
        out["param_dtype"] = FLAGS.param_dtype
    return out


def _load_state(path: Path) -> dict:
    if not path.exists():
        return {"settings": _settings(), "stages": {}}
    state = json.loads(path.read_text())
    if state["settings"] != _settings():
        diff = {k: (state["settings"].get(k), v) for k, v in _settings().items() if state["settings"].get(k) != v}
        raise app.UsageError(f"{path.parent} was built with other settings (was, now): {diff}; rerun with the "
                             f"settings it was built with, or use another --work")
    return state


def _write_state(path: Path, state: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(state, indent=1))
    os.replace(tmp, path)


def run_stage(stage: Stage, log_path: Path, env: dict, console: Console) -> dict:
    """Runs one stage, its output appended to log_path and echoed; returns its figures."""
    cmd = [sys.executable, "-m", f"experiments.{stage.args[0]}", *stage.args[1:]]
    figures, text = {}, []
    with open(log_path, "a") as log:
        log.write(f"$ {' '.join(cmd)}\n")
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for line in proc.stdout:
            log.write(line)
            log.flush()
            text.append(line)
            if line.startswith("{") or "success" in line or "kept" in line or "DAgger" in line or "Error" in line:
                console.print(f"  [dim]{stage.name}[/dim] {line.rstrip()[:200]}", markup=True, highlight=False)
        rc = proc.wait()
    if rc != 0:
        raise RuntimeError(f"stage {stage.name} failed (exit {rc}); its log: {log_path}\n{''.join(text[-15:])}")
    joined = "".join(text)
    for name, pattern in stage.figures.items():
        found = re.findall(pattern, joined)
        if found:
            figures[name] = found[-1]
    return figures


def install(w: Path) -> None:
    """Copies the final target, drafter and datastore over checkpoints/ (each replaced whole,
    via a temporary sibling, so an interrupted copy never leaves a half checkpoint)."""
    pairs = [(_policy(w, _final_round()), ROOT / "checkpoints" / "vla"), (w / "drafter", ROOT / "checkpoints" / "drafter"),
             (w / "datastore", ROOT / "checkpoints" / "datastore")]
    for src, dst in pairs:
        if not src.exists():
            raise RuntimeError(f"cannot install {dst.name}: {src} does not exist")
    for src, dst in pairs:
        tmp = dst.with_name(f".{dst.name}.installing")
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(src, tmp)
        old = dst.with_name(f".{dst.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        if dst.exists():
            os.replace(dst, old)
        os.replace(tmp, dst)
        shutil.rmtree(old, ignore_errors=True)


def main(argv):
    del argv
    bad = sorted(set(FLAGS.skip) - set(SKIPPABLE))
    if bad:
        raise app.UsageError(f"--skip: unknown stages {bad}; valid: {', '.join(SKIPPABLE)}")
    if FLAGS.steps < (0 if FLAGS.start else 1):
        raise app.UsageError(f"--steps must be >= 1 (>= 0 with --start), got {FLAGS.steps}")
    if FLAGS.rollout_episodes < 0:
        raise app.UsageError(f"--rollout_episodes must be >= 0, got {FLAGS.rollout_episodes}")
    if FLAGS.datastore_source == "rollouts" and not FLAGS.rollout_episodes and "datastore" not in FLAGS.skip:
        raise app.UsageError("--datastore_source=rollouts builds the datastore from the target's own rollouts: "
                             "give --rollout_episodes > 0 (episodes per task)")
    for name in ("demo_episodes", "dagger_episodes", "dagger_steps", "drafter_steps", "num_envs",
                 "eval_episodes", "batch_size"):
        if getattr(FLAGS, name) < 1:
            raise app.UsageError(f"--{name} must be >= 1, got {getattr(FLAGS, name)}")
    _schedule("label_sigma_bins")
    if FLAGS.expert_rot_gain is not None and FLAGS.expert_rot_gain <= 0:
        raise app.UsageError(f"--expert_rot_gain must be > 0, got {FLAGS.expert_rot_gain}")
    if FLAGS.rounds < 0:
        raise app.UsageError(f"--rounds must be >= 0, got {FLAGS.rounds}")
    if FLAGS.fresh_weight < 0:
        raise app.UsageError(f"--fresh_weight must be >= 0 (0: the fresh round trains on its own data alone), got "
                             f"{FLAGS.fresh_weight}")
    if FLAGS.train_devices < 0:
        raise app.UsageError(f"--train_devices must be >= 0 (0: all local devices), got {FLAGS.train_devices}")
    if not FLAGS.dry_run:
        devices = FLAGS.train_devices or local_device_count()
        if FLAGS.batch_size % devices:
            raise app.UsageError(f"--batch_size={FLAGS.batch_size} must be a multiple of the {devices} devices each "
                                 f"training stage splits it over (--train_devices={FLAGS.train_devices}, 0: all local "
                                 f"devices); pass --train_devices or another --batch_size")
    _schedule("beta", 1.0)
    from envs import tasks as tasks_lib  # noqa: PLC0415

    try:
        tasks_lib.get_tasks(FLAGS.suites, FLAGS.tasks or None)
        if FLAGS.weights_from:  # resolved to explicit entries, so build.json records the weights themselves
            FLAGS.suite_weights = cli.failure_weights(FLAGS.weights_from) + list(FLAGS.suite_weights)
        tasks_lib.parse_suite_weights(FLAGS.suite_weights)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
    if FLAGS.start and not (Path(FLAGS.start) / "0").is_dir():
        raise app.UsageError(f"--start {FLAGS.start}: no policy checkpoint there")
    if FLAGS.fresh_round and "eval" in FLAGS.skip:
        raise app.UsageError("--fresh_round weighs its collections by the evaluation's failures: drop eval from --skip")
    if FLAGS.install and FLAGS.skip:
        raise app.UsageError("--install needs every stage (drop --skip)")
    w = Path(FLAGS.work).absolute()
    if FLAGS.dry_run:
        stages = plan(w)
        for stage, runs in zip(stages, to_run(stages)):
            status = "to run" if runs else "done" if stage.done() else "not needed: every stage that reads it is done"
            print(f"{stage.name} ({status}): python -m experiments.{' '.join(stage.args)}")
        return
    (w / "logs").mkdir(parents=True, exist_ok=True)
    state_path = w / "build.json"
    state = _load_state(state_path)
    _write_state(state_path, state)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.setdefault("JAX_COMPILATION_CACHE_DIR", str(w / "jax_cache"))
    console = Console()
    stages = plan(w)
    t_all = time.perf_counter()
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total} stages"),
                  TimeElapsedColumn(), console=console) as bar:
        job = bar.add_task("building", total=len(stages))
        for stage, runs in zip(stages, to_run(stages)):
            if not runs:
                bar.update(job, advance=1, description=f"{stage.name}: {'done' if stage.done() else 'not needed'}")
                continue
            bar.update(job, description=f"{stage.name}: running")
            t0 = time.perf_counter()
            figures = run_stage(stage, w / "logs" / f"{stage.name}.log", env, console)
            if not stage.done():
                raise RuntimeError(f"stage {stage.name} ended without completing {stage.output}")
            state["stages"][stage.name] = {"seconds": round(time.perf_counter() - t0, 1), **figures}
            _write_state(state_path, state)
            console.print(f"[bold]{stage.name}[/bold] done in {time.perf_counter() - t0:.0f}s {figures}")
            bar.update(job, advance=1)
    if FLAGS.install:
        install(w)
        console.print("installed into checkpoints/: vla, drafter, datastore")
    console.print(f"built in {time.perf_counter() - t_all:.0f}s (this invocation); stages: {json.dumps(state['stages'])}")


if __name__ == "__main__":
    cli.run(main)
