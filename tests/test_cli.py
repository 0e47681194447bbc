"""A user's mistake on the command line: one line naming the problem, exit status 2, no
traceback and no usage text, before anything loads or compiles."""

import os
from pathlib import Path
import subprocess
import sys

import pytest

CASES = [
    ("evaluate", ["--suites=nope"], "unknown suite"),
    ("evaluate", ["--episodes=-1"], "episodes"),
    ("evaluate", ["--method=ar", "--top_k=4"], "--method=ar takes none of --top_k"),
    ("evaluate", ["--method=ar", "--checkpoint=/nonexistent/vla"], "no policy checkpoint there"),
    ("evaluate", ["--method=nope"], "ar|drafter|expert|heisd|retrieval"),
    ("evaluate", ["--num_envs=8", "--tail_envs=8"], "tail_envs must be 0 (off) or in 1..7"),
    ("sweep", ["--num_envs=8,16", "--tail_envs=12"], "tail_envs must be 0 (off) or in 1..7"),
    ("evaluate", ["--num_envs=-1"], "num_envs"),
    ("sweep", ["--num_envs=8,-2"], "num_envs must be >= 1"),
    ("evaluate", ["--physics=max_contact=32"], "with a field among integrator, force_limits"),
    ("sweep", ["--physics=ls_iterations=0"], "ls_iterations must be at least 1"),
    ("bench_env", ["--physics=;max_contacts=x"], "max_contacts takes a int"),
    ("studies.compile_parts", ["--method=ar", "--checkpoint=/nonexistent/vla"], "no policy checkpoint there"),
    ("studies.camera_visibility", ["--suites=nope"], "unknown suite"),
    ("bench_decode", ["--batch_sizes=1,x"], "positive integers"),
    ("studies.solver_iterations", ["--tolerances=1e-5,x"], "takes non-negative numbers"),
    ("collect_demos", ["--suites=nope", "--out=/nonexistent/demos"], "unknown suite"),
    ("collect_demos", ["--suite_weights=spatial:2,longg:3", "--out=/nonexistent/demos"], "bad suite weight 'longg:3'"),
    ("collect_demos", ["--devices=9", "--out=/nonexistent/demos"], "--devices=9: 1 local devices here"),
    ("collect_demos", ["--keep_total", "--out=/nonexistent/demos"], "--keep_total needs --weights_from"),
    ("train", ["--demos=/nonexistent/demos", "--out=/nonexistent/run"], "not a complete dataset"),
    ("train", ["--weights_from=/nonexistent/eval.json", "--out=/nonexistent/run"], "weights from /nonexistent/eval.json"),
    ("ship_autotune", ["--methods=ar,nope"], "unknown ['nope']; choose from ['ar', 'drafter', 'expert'"),
    ("ship_autotune", ["--out=/nonexistent/x.txt"], "--out must end in .pbtxt"),
    ("evaluate", ["--method=expert", "--target_scale=llama-1b"], "--method=expert takes none of --target_scale"),
    ("bench_methods", ["--target_scale=huge"], "<shipped|llama2-7b|llama-1b>"),
    ("bench_methods", ["--reps=0"], "flag --reps=0: 0 is not a positive integer"),
    ("bench_methods", ["--methods=ar;heisd:budget=fixed;heisd", "--batch_sizes=1", "--record_envs=1",
                       "--cost_cache=/nonexistent/costs"], "has none for heisd at batch [1]: add --calibrate_costs"),
    ("bench_methods", ["--methods=ar;heisd:budget=fixed,n_candidates=16", "--batch_sizes=1", "--record_envs=1"],
     "heisd:budget=fixed,n_candidates=16: 16 retrieved + 4 recent candidates need"),
    ("bench_scale", ["--target_scale=llama3"], "<shipped|llama2-7b|llama-1b>"),
    ("scale_check", ["--dtypes=float16"], "--dtypes: unknown ['float16']; valid: float32, bfloat16"),
    ("studies.op_invariance", ["--numerics=float16"], "valid are bfloat16, f32_act_bf16_products, float32"),
    ("studies.invariant_tiles", ["--tiles=64x48x32"], "n=48: must be a power of two >= 16"),
    ("studies.trace_decode", ["--functions=prefill,prefil"], "--functions ['prefil']: valid are ['ar', 'prefill'"),
    ("studies.expert_gain", ["--gains=1.2,0"], "--gains must be > 0"),
    ("studies.failure_modes", ["--method=ar", "--top_k=4"], "--method=ar takes none of --top_k"),
    ("studies.failure_modes", ["--suites=spatial", "--tasks=nope"], "unknown task(s) ['nope'] in suite(s) ['spatial']"),
    ("studies.budget_replay", ["--tables=experiments/results/costs/cost_table_bf16_target_b16_h200.json"],
     "prices batch 16: the replay is at batch 1"),
    ("studies.budget_replay", ["--settings=target_scale=llama2-7b,top_k=3"],
     "--settings: ['top_k'] are set by each replayed option"),
    ("profile", ["--compiler_options=xla_bogus=1"], "No such compile option: 'xla_bogus'"),
    ("profile", ["--compiler_options=xla_gpu_deterministic_ops"], "is not key=value"),
    ("profile", ["--parts=prefill,verify"], "--parts: unknown ['verify']; valid parts: ['prefill', 'prefill+cand'"),
]


@pytest.mark.parametrize("module,args,expected", CASES, ids=[f"{m}:{' '.join(a)}" for m, a, _ in CASES])
def test_bad_flag_is_one_line(module, args, expected, tmp_path):
    r = subprocess.run([sys.executable, "-m", f"experiments.{module}", *args], capture_output=True, text=True,
                       timeout=120)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith(f"python -m experiments.{module}: error: ")
    assert expected in lines[0]


def test_an_attention_this_machine_cannot_run_is_refused_before_recording(tmp_path):
    import jax

    if jax.default_backend() == "gpu":
        pytest.skip("cuDNN's attention runs here")
    for module, args in (("bench_methods", ["--attention=cudnn", "--dtype=bfloat16", "--methods=ar"]),
                         ("evaluate", ["--method=ar", "--attention=cudnn", "--dtype=bfloat16"])):
        test_bad_flag_is_one_line(module, args, "attention 'cudnn' runs on a GPU, not on cpu; valid here: auto, xla",
                                  tmp_path)


def test_bad_flag_writes_nothing(tmp_path):
    out = tmp_path / "eval.json"
    out.write_text("{}")
    r = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--suites=nope", f"--out={out}"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert out.read_text() == "{}"


def test_sweep_refuses_a_missing_cost_table_before_writing_anything(tmp_path):
    out = tmp_path / "sweep.jsonl"
    r = subprocess.run([sys.executable, "-m", "experiments.sweep", "--methods=heisd", "--suites=goal",
                        "--tasks=red_block_plate", "--episodes=1", "--num_envs=1", f"--cost_cache={tmp_path / 'costs'}",
                        f"--out={out}"], capture_output=True, text=True, timeout=300)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "budget=auto needs a decode-cost table" in lines[0] and "heisd at batch [1]" in lines[0]
    assert not out.exists()


def test_method_flags_are_the_settings_fields():
    from absl import app, flags

    from experiments import method_flags
    from heisd_jax.harness import methods

    fv = flags.FlagValues()
    names = method_flags.define(flag_values=fv)
    fields = {key for name in methods.DECODING_METHODS for key in methods.settings(name)}
    assert set(names) == fields | {methods.PRESET} and len(names) == len(fields) + 1
    assert fv["budget"].parser.enum_values == list(methods.settings("heisd")["budget"].choices)
    assert "heisd auto" in fv["budget"].help and "retrieval fixed" in fv["budget"].help  # each method's default
    fv(["prog", "--k_skip=2", "--skip=false", "--budget_trees=4x2x8"])
    assert method_flags.given("heisd", fv) == {"k_skip": 2, "skip": False, "budget_trees": "4x2x8"}
    with pytest.raises(app.UsageError, match="--method=drafter takes none of --skip, --k_skip, --budget_trees"):
        method_flags.given("drafter", fv)
    fv.unparse_flags()
    fv(["prog", "--budget=fixed", "--budget_margin=0.2"])
    with pytest.raises(app.UsageError, match="budget_margin is only used with budget=auto"):
        method_flags.given("heisd", fv)
    fv.unparse_flags()
    fv(["prog", "--preset=batch16", "--row_buckets=8"])  # a preset's settings, the given one replacing its own
    assert method_flags.given("heisd", fv) == {**methods.PRESETS["heisd"]["batch16"], "row_buckets": 8}
    with pytest.raises(app.UsageError, match="--method=ar takes none of --row_buckets, --preset"):
        method_flags.given("ar", fv)
    assert method_flags.given("ar", flags.FlagValues()) == {}


def test_suite_weights_parse_and_name_the_bad_entry():
    from envs import tasks

    assert tasks.parse_suite_weights(["spatial:2", "long:3"]) == {"spatial": 2, "long": 3}
    assert tasks.parse_suite_weights([]) == {}
    for bad in ("spatial", "spatial:0", "spatial:x", "nope:2"):
        with pytest.raises(ValueError, match=f"bad suite weight '{bad}'.*'spatial', 'object', 'goal', 'long'"):
            tasks.parse_suite_weights([bad])
    weights = tasks.parse_suite_weights(["spatial:3", "far_plate_block_basket:5"])
    by_name = {t.name: t for t in tasks.ALL_TASKS}
    assert tasks.episode_weight(by_name["far_plate_block_basket"], weights) == 5  # the task's own weight wins
    assert tasks.episode_weight(by_name["left_block_plate"], weights) == 3  # its suite's
    assert tasks.episode_weight(by_name["pick_red_block"], weights) == 1  # not named


def test_collection_batches_hold_one_time_limit_each_and_share_one_size():
    from experiments.collect_demos import horizon_batches

    limits = [220, 420, 220]
    pairs = [(t, e) for t in range(3) for e in range(5)]
    batches = horizon_batches(pairs, limits, num_envs=4)
    assert sorted(p for _, _, chunk in batches for p in chunk) == sorted(pairs)  # every episode once
    for limit, size, chunk in batches:
        assert {limits[t] for t, _ in chunk} == {limit} and len(chunk) <= size <= 4
    # 10 episodes of limit 220 in 3 batches, 5 of limit 420 in 2 of 3 and 2: as few batches as
    # each limit needs, all of one size (one compiled program runs them all).
    assert [(n, s, len(c)) for n, s, c in batches] == [(220, 4, 4), (220, 4, 4), (220, 4, 2), (420, 4, 3), (420, 4, 2)]
    # Split over 2 devices: every size even, the same episodes.
    halves = horizon_batches(pairs, limits, num_envs=4, multiple=2)
    assert sorted(p for _, _, chunk in halves for p in chunk) == sorted(pairs)
    assert all(size % 2 == 0 and len(chunk) <= size <= 4 for _, size, chunk in halves)


def test_ship_autotune_refuses_a_machine_without_a_gpu_before_compiling(tmp_path):
    out = tmp_path / "xla_autotune.pbtxt"
    r = subprocess.run([sys.executable, "-m", "experiments.ship_autotune", f"--out={out}"], capture_output=True,
                       text=True, cwd=Path(__file__).resolve().parents[1], timeout=300,
                       env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert r.returncode == 2 and "only on a GPU" in r.stderr, r.stderr[-2000:]
    assert not out.exists()


def test_command_line_records_the_users_xla_flags(monkeypatch):
    """A results file's command reruns the measurement: XLA_FLAGS the user set (they change
    what a run measures, e.g. command buffers) come first; the project's own do not."""
    from envs import _xla
    from experiments import cli

    monkeypatch.setattr(sys, "argv", ["x", "--batch=1", "--methods=ar;heisd"])
    monkeypatch.setattr(_xla, "USER_FLAGS", "")
    plain = cli.command_line()
    assert "XLA_FLAGS" not in plain and plain.endswith("--batch=1 '--methods=ar;heisd'")
    monkeypatch.setattr(_xla, "USER_FLAGS", "--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL")
    assert cli.command_line() == "XLA_FLAGS=--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL " + plain


def test_config_digest_is_the_settings_in_effect_not_those_given():
    """Results record this digest beside the given settings: the same config reached by other
    words is the same digest, another default (or value) is another."""
    from experiments import cli

    default = cli.config_digest("heisd", {})
    spelled_out = {"budget": "auto", "acceptance": "strict", "retrieval_acceptance": "seq_relaxed", "skip": True}
    assert cli.config_digest("heisd", spelled_out) == default
    assert cli.config_digest("heisd", {"acceptance": "token_relaxed"}) != default
    assert cli.config_digest("ar", {}) != cli.config_digest("ar", {"dtype": "bfloat16"})


def test_the_first_signal_asks_a_run_to_stop_and_the_second_ends_it():
    """`cli.StopOnSignals`: SIGTERM only sets the flag a run reads between rounds, and puts the
    handlers back, so a second signal takes its default course."""
    import signal

    from experiments import cli

    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    stop = cli.StopOnSignals()
    try:
        assert not stop()
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop() and stop.exit_code == 128 + signal.SIGTERM
        assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    finally:
        signal.signal(signal.SIGTERM, before[0])
        signal.signal(signal.SIGINT, before[1])


def test_a_stopped_run_exits_without_joining_a_compile_thread():
    """`StopOnSignals.exit`: the exit code of the signal, the output flushed, and no wait for a
    thread still working (a queue's tail compiling in the background)."""
    import time

    code = ("import os, signal, threading, time\n"
            "from experiments import cli\n"
            "stop = cli.StopOnSignals()\n"
            "threading.Thread(target=time.sleep, args=(60,)).start()\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "print('saved', end='')\n"
            "stop.exit()\n")
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert (done.returncode, done.stdout) == (143, "saved") and time.perf_counter() - t0 < 30
