"""experiments.eval_report: what `evaluate` prints at the end of a run, from the file it wrote."""

import copy
import gzip
import json
from pathlib import Path

from experiments import eval_report

RESULTS = Path(__file__).resolve().parents[1] / "experiments" / "results"


def _read(name: str) -> dict:
    path = RESULTS / name
    with (gzip.open(path, "rt") if path.suffix == ".gz" else open(path)) as f:
        return json.load(f)


def test_report_of_a_resumed_7b_file_is_what_its_run_printed():
    """The committed long suite (a run resumed after a cut one, on one H200) and the job log
    of the run that wrote it: the report made from the file is the log's closing lines."""
    data = _read("eval_7b_h200/eval_heisd_fixed_7b_bf16_long.json.gz")
    log = (RESULTS / "eval_7b_h200" / "job_heisd_long_bf92d22.log").read_text().splitlines()
    first = log.index(next(line for line in log if line.startswith("suite ")))
    last = log.index(next(line for line in log if line.startswith("results: ")))
    out = log[last][len("results: "):]
    assert eval_report.final_report(data, camera=True, out=out).splitlines() == ["", *log[first:last + 1]]


def test_a_rerun_with_nothing_left_reports_the_earlier_runs_speed_only():
    data = copy.deepcopy(_read("eval_7b_h200/eval_heisd_fixed_7b_bf16_long.json.gz"))
    data["timing"].update(batches=0, batch_seconds=0.0, control_steps=0, env_steps=0)
    data["timing"].pop("ms_per_control_step")
    text = eval_report.final_report(data, camera=False, out="x")
    assert "ms per control step (" not in text  # this run's: none
    assert "all 2 runs of this file: 827.1 ms per control step over 588 control steps" in text


def test_report_of_a_static_batch_ar_file_and_of_the_expert():
    ar = eval_report.final_report(_read("main_job_cpu.json"), camera=True, out="x").splitlines()
    assert ar[2].split() == ["spatial", "5", "0.800", "90.0", "7.00", "1.00", "630"]
    assert ar[3].startswith("331.6 ms per control step (5 envs: decode + physics + camera)")
    assert ar[-2].startswith("compile: 71.9s: trace 11.2s")  # one program: no queue's parts
    expert = eval_report.final_report(_read("substeps_cpu/eval_expert_sub5_cpu.json.gz"), camera=False, out="x")
    row = expert.splitlines()[2].split()
    assert row[4:] == ["-", "-", "-"]  # no target passes to count
    assert "+ camera" not in expert
