"""experiments.compare_evals: paired success counts and the success guard."""

import gzip
import json

import pytest

from experiments import cli, compare_evals


def result(method, successes: dict[str, list[bool]], suite_of: dict[str, str], skipped=0.0, passes=70.0):
    episodes = {t: [dict(success=s, steps=10, decode=dict(target_passes=passes, skipped=skipped)) for s in ss]
                for t, ss in successes.items()}
    return dict(settings=dict(method=method, tasks=list(successes)), episodes=episodes,
                summary=dict(tasks={t: dict(suite=suite_of[t]) for t in successes}))


SUITE_OF = {"a": "spatial", "b": "spatial", "c": "long"}
BASE = result("ar", {"a": [True, True, False, True], "b": [True] * 4, "c": [True, False, True, True]}, SUITE_OF)


def test_paired_counts_rates_and_guard():
    other = result("heisd", {"a": [True, False, True, True], "b": [True] * 4, "c": [False, False, True, True]},
                   SUITE_OF, skipped=2.0, passes=28.0)
    r = compare_evals.compare(BASE, other, tolerance=2.0)
    sp, lo = r["suites"]["spatial"], r["suites"]["long"]
    assert (sp["base_only"], sp["other_only"], sp["rate"], sp["base_rate"]) == (1, 1, 7 / 8, 7 / 8)
    assert (lo["base_only"], lo["other_only"], lo["diff_points"]) == (1, 0, -25.0)
    assert (r["base_only"], r["other_only"], r["guard"], r["worst_diff_points"]) == (2, 1, False, -25.0)
    assert r["skipped_share"] == pytest.approx(0.2)
    assert (r["target_passes_per_episode"], r["base_target_passes_per_episode"]) == (28.0, 70.0)
    assert "| 28 (2.50x) |" in compare_evals.table(BASE, [r], 2.0)  # the saving per episode
    assert list(r["suites"]) == ["spatial", "long"]  # the evaluation's order
    assert compare_evals.compare(BASE, other, tolerance=25.0)["guard"]


def test_steps_of_successful_episodes_only():
    """A slower policy shows in the steps its successes take; failures (time-outs) do not count."""
    slow = result("heisd", {"a": [True, True, False, True], "b": [True] * 4, "c": [True, False, True, True]}, SUITE_OF)
    for i, e in enumerate(e for eps in slow["episodes"].values() for e in eps):
        e["steps"] = 1000 if not e["success"] else 10 + 10 * i  # successes: 10, 20, 40, ..., 120
    r = compare_evals.compare(BASE, slow, tolerance=2.0)
    wins = [10 + 10 * i for i, e in enumerate(e for eps in slow["episodes"].values() for e in eps) if e["success"]]
    assert r["success_steps"]["mean"] == pytest.approx(sum(wins) / len(wins))
    assert r["success_steps"]["p90"] <= max(wins) < 1000
    assert r["base_success_steps"] == dict(mean=10.0, p90=10.0)
    text = compare_evals.table(BASE, [r], 2.0)
    assert "steps / success (p90)" in text and "| 10 (10) |" in text
    none = result("heisd", {t: [False] * 4 for t in "abc"}, SUITE_OF)
    assert compare_evals.compare(BASE, none, tolerance=2.0)["success_steps"] is None


def test_labels_name_the_settings_given_and_the_commit():
    r = dict(result("heisd", {"a": [True]}, SUITE_OF), commit="abcdef0123")
    r["settings"].update(k_skip=3, datastore="/tmp/x/store_ro", checkpoint="ckpt")
    assert compare_evals.label(r) == "heisd:datastore=store_ro,k_skip=3 @abcdef0"
    assert compare_evals.label(BASE) == "ar"


def test_an_evaluation_against_itself_differs_nowhere():
    r = compare_evals.compare(BASE, BASE, tolerance=0.0)
    assert r["guard"] and r["base_only"] == r["other_only"] == 0 and r["mean_rate"] == r["base_mean_rate"]


def test_unpaired_evaluations_and_bad_files_are_refused(tmp_path):
    fewer = result("ar", {"a": [True] * 3, "b": [True] * 4, "c": [True] * 4}, SUITE_OF)
    with pytest.raises(ValueError, match="not paired"):
        compare_evals.compare(BASE, fewer, tolerance=2.0)
    partial = result("heisd", {t: [e["success"] for e in BASE["episodes"][t]] for t in "abc"}, SUITE_OF)
    partial["episodes"]["c"][1] = None  # saved mid-queue, not finished
    with pytest.raises(ValueError, match="the other has 1 episodes not run yet"):
        compare_evals.compare(BASE, partial, tolerance=2.0)
    bad = tmp_path / "x.json"
    bad.write_text(json.dumps({"summary": {}}))
    with pytest.raises(ValueError, match="not an experiments.evaluate result"):
        cli.load_eval_results(str(bad))


def test_a_gzipped_result_loads_as_the_plain_one(tmp_path):
    plain, packed = tmp_path / "e.json", tmp_path / "e.json.gz"
    plain.write_text(json.dumps(BASE))
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    assert cli.load_eval_results(str(packed)) == cli.load_eval_results(str(plain)) == BASE


def test_evaluations_of_disjoint_tasks_join_into_the_whole(tmp_path):
    """One run per suite, joined with '+', compares as the one run over every task."""
    other = result("heisd", {"a": [True, False, True, True], "b": [True] * 4, "c": [False, False, True, True]},
                   SUITE_OF)
    parts = [result("heisd", {t: [e["success"] for e in other["episodes"][t]] for t in ts}, SUITE_OF)
             for ts in (["a", "b"], ["c"])]
    paths = []
    for i, p in enumerate(parts):
        paths.append(tmp_path / f"part{i}.json")
        paths[-1].write_text(json.dumps(dict(p, commit="abcdef0123")))
    joined = compare_evals.load("+".join(map(str, paths)))
    assert joined["settings"]["tasks"] == ["a", "b", "c"] and joined["commit"] == "abcdef0123"
    whole, split = compare_evals.compare(BASE, other, 2.0), compare_evals.compare(BASE, joined, 2.0)
    assert {k: v for k, v in split.items() if k != "label"} == {k: v for k, v in whole.items() if k != "label"}
    with pytest.raises(ValueError, match=r"tasks only in the baseline: c \(1\).*join with '\+'"):
        compare_evals.compare(BASE, parts[0], 2.0)


def test_a_join_refuses_other_settings_and_repeated_tasks():
    a = result("heisd", {"a": [True]}, SUITE_OF)
    a["settings"].update(checkpoint="/tmp/one/vla", contents={"checkpoint": "deddfac7"})
    b = result("heisd", {"b": [True]}, SUITE_OF)  # the same file read from another path: joins
    b["settings"].update(checkpoint="/root/two/vla", contents={"checkpoint": "deddfac7"})
    assert compare_evals.join([a, b])["settings"]["tasks"] == ["a", "b"]
    b["settings"]["contents"] = {"checkpoint": "0123abcd"}
    with pytest.raises(ValueError, match="part 2 differs in contents"):
        compare_evals.join([a, b])
    with pytest.raises(ValueError, match="part 2 differs in .*method"):
        compare_evals.join([a, result("ar", {"b": [True]}, SUITE_OF)])
    with pytest.raises(ValueError, match="both hold task 'a' \\(parts 1 and 2\\)"):
        compare_evals.join([a, dict(result("heisd", {"a": [False]}, SUITE_OF), settings=a["settings"])])


def test_common_tasks_restrict_every_evaluation_to_the_shared_ones():
    part = result("heisd", {"a": [True, False, True, True], "c": [False] * 4}, SUITE_OF)
    (base, other), left_out = compare_evals.common([BASE, part])
    assert left_out == ["b"] and list(base["episodes"]) == ["a", "c"] == base["settings"]["tasks"]
    r = compare_evals.compare(base, other, 2.0)
    assert (r["suites"]["spatial"]["base_only"], r["suites"]["spatial"]["episodes"]) == (1, 4)
    assert r["suites"]["long"]["diff_points"] == -75.0


def test_ended_only_compares_the_episodes_every_evaluation_has_ended():
    """A run cut mid-queue compares on the initial states it has ended, paired as in the whole run."""
    cut = result("heisd", {"a": [True, False, True, True], "b": [True] * 4, "c": [False, False, True, True]}, SUITE_OF)
    cut["episodes"]["a"][1] = cut["episodes"]["c"][0] = None
    del cut["episodes"]["b"], cut["summary"]["tasks"]["b"]  # not started: only its settings name it
    cut["settings"]["episodes_per_task"] = 4
    cut = compare_evals.with_unstarted(cut)
    assert cut["episodes"]["b"] == [None] * 4
    (base, other), unended = compare_evals.ended([BASE, cut])
    assert unended == 6 and list(base["episodes"]) == ["a", "c"] == other["settings"]["tasks"]
    assert [e["success"] for e in base["episodes"]["c"]] == [False, True, True]  # states 1-3, paired with the cut run's
    r = compare_evals.compare(base, other, 2.0)
    assert r["suites"]["spatial"]["episodes"] == 3 and r["suites"]["long"]["base_only"] == 0
    with pytest.raises(ValueError, match="not run yet"):
        compare_evals.compare(BASE, cut, 2.0)
    (base2, other2), _ = compare_evals.ended(compare_evals.common([BASE, cut])[0])  # both flags
    assert (base2, other2) == (base, other)
    assert compare_evals.ended([BASE, BASE]) == ([BASE, BASE], 0)
    with pytest.raises(ValueError, match="not paired.*--common_tasks"):  # a task one of them lacks
        compare_evals.ended([BASE, result("heisd", {"a": [True] * 4}, SUITE_OF)])
