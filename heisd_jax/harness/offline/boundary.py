"""Calibrates HeiSD's kinematic boundary and verify-skip threshold from held-out demo steps
(`python -m experiments.calibrate_boundary`, which writes the record `calibrate` returns
to <datastore>/boundary.json; `heisd_jax.harness.methods.load_calibration` reads it back).

`closed_loop_steps` turns a recorded closed-loop rollout into the same inputs (the
draft-source analysis, `experiments.studies.draft_sources`). `measure` decodes every step twice with a heisd configuration: retrieval first
(the candidates verified, drafter rounds for what they leave) and drafter SD alone, and
records target passes per action (TPA), the retrieval draft's accepted length and the
nearest key's distance, beside the step's fused kinematic metric. `calibrate` turns those
arrays into the thresholds (the paper's "complementary advantages" analysis, binned by
metric quantiles):
  tau_on   the lowest metric bin edge from which retrieval needs more target passes than
           the drafter (the metric's top if it never does), at least the first bin's top
  tau_off  `hysteresis` x tau_on
  skip_eps the largest nearest-key distance under which at least `skip_precision` of the
           retrieval drafts were accepted whole (counting only from `min_skip_steps` steps;
           0 if none)
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from heisd_jax import hybrid, kinematics, retrieval, vla
from heisd_jax.harness.offline.datastore import episode_history, in_batches
from heisd_jax.tokenizer import ACTION_DIM, ActionTokenizer


@dataclasses.dataclass(frozen=True)
class BoundaryRule:
    bins: int = 10  # metric bins (quantiles)
    hysteresis: float = 0.7  # tau_off = hysteresis * tau_on
    skip_precision: float = 0.9  # verify-skip: whole-acceptance rate required below skip_eps
    min_skip_steps: int = 20  # skip_eps is read only where at least this many steps lie below it

    def __post_init__(self):
        if not 0 < self.hysteresis < 1 or not 0 < self.skip_precision <= 1 or self.bins < 2:
            raise ValueError("need 0 < hysteresis < 1, 0 < skip_precision <= 1 and bins >= 2")


MEASURED = ("metric", "tpa_retrieval", "accepted", "tpa_drafter", "dist")  # `measure`'s arrays, [N] each


def measure(params: dict, cfg: vla.VLAConfig, hcfg: hybrid.HybridConfig, key_spec: retrieval.KeySpec,
            tok: ActionTokenizer, steps: dict, batch: int, drafter_alone: bool = True) -> dict[str, np.ndarray]:
    """The arrays of `MEASURED` [N] for N held-out steps. params: {"target", "drafter",
    "store"}; steps: image [N, H, W, 3], instruction [N, L], proprio [N, 8], prev (the
    actions before each step) [N, history, 7], task [N], feat (kinematic features) [N, 5],
    and optionally key [N, dim]: the retrieval keys themselves, for a store keyed otherwise
    than by `key_spec` (default: `retrieval.make_keys` of prev and proprio); recent [N, R, 7]
    token ids with recent_valid [N, R]: the env's last executed actions, verified after the
    retrieved candidates (as `hybrid.step` does with `recent_candidates`).
    Decoded `batch` steps at a time, the last batch padded by wrapping (static shape).
    `drafter_alone=False` skips the drafter-only decode (its TPA is then NaN), for comparing
    datastores on the same steps."""
    metric = np.asarray(kinematics.fused_metric(jnp.asarray(steps["feat"]), hcfg.metric))

    @jax.jit
    def both_ways(p, image, instruction, proprio, prev, task, key, recent):
        obs = vla.Observation(image=image, instruction=instruction, proprio=proprio)
        key = retrieval.make_keys(key_spec, tok, prev, proprio) if key is None else key
        cand, dist, valid = retrieval.query(p["store"], key, task, hcfg.n_candidates, hcfg.max_dist)
        if recent is not None:
            cand, valid = jnp.concatenate([cand, recent[0]], 1), jnp.concatenate([valid, recent[1]], 1)
        no = jnp.zeros(task.shape, bool)
        _, r = hybrid.decode(p, cfg, hcfg, obs, cand, valid, ~no, no)
        alone = hybrid.decode(p, cfg, hcfg, obs, cand, valid, no, no)[1]["target_passes"] if drafter_alone else \
            jnp.full(task.shape, jnp.nan)
        return r["target_passes"], r["retrieval_accepted"], alone, dist[:, 0]

    def rows(idx):
        cols = (jnp.asarray(steps[k][idx]) for k in ("image", "instruction", "proprio", "prev", "task"))
        return both_ways(params, *cols, None if "key" not in steps else jnp.asarray(steps["key"][idx]),
                         None if "recent" not in steps else (jnp.asarray(steps["recent"][idx]),
                                                             jnp.asarray(steps["recent_valid"][idx])))
    return {"metric": metric, **dict(zip(MEASURED[1:], in_batches(rows, len(metric), batch)))}


def _row(measured: dict, m: np.ndarray) -> dict:
    """Steps, mean TPA both ways, mean accepted length and whole-acceptance rate over mask m."""
    return {"steps": int(m.sum()), "tpa_retrieval": float(measured["tpa_retrieval"][m].mean()),
            "tpa_drafter": float(measured["tpa_drafter"][m].mean()),
            "retrieval_accepted": float(measured["accepted"][m].mean()),
            "retrieval_whole": float((measured["accepted"][m] == ACTION_DIM).mean())}


def closed_loop_steps(traj: dict, final_step: np.ndarray, instructions: np.ndarray, tasks: np.ndarray,
                      history: int) -> tuple[dict, np.ndarray]:
    """The running steps of a recorded [T, B] trajectory as `boundary.measure`'s inputs, and
    the expert's phase of each [N]. Rows are env-major (env 0's steps in order, then env 1's).
    The action history of a step is what the env executed before it (the policy's actions:
    the teacher only watches), the previous velocity the step before's (zero at the start)."""
    cols = {k: [] for k in ("image", "instruction", "proprio", "prev", "task", "feat")}
    phase = []
    for b in range(len(final_step)):
        n = int(final_step[b])
        if n == 0:
            continue
        vel = np.asarray(traj["ee_vel"][:n, b], np.float32)
        prev_vel = np.concatenate([np.zeros((1, 3), np.float32), vel[:-1]])
        cols["feat"].append(np.asarray(kinematics.features(vel, traj["ee_ang_vel"][:n, b], traj["ee_acc"][:n, b],
                                                           traj["gripper_vel"][:n, b], prev_vel)))
        cols["prev"].append(episode_history(np.asarray(traj["policy_action"][:n, b], np.float32), history))
        cols["image"].append(traj["image"][:n, b])
        cols["proprio"].append(traj["proprio"][:n, b])
        cols["instruction"].append(np.repeat(instructions[b][None], n, 0))
        cols["task"].append(np.full(n, tasks[b], np.int32))
        phase.append(np.asarray(traj["teacher_stats"]["phase"][:n, b], np.int32))
    if not phase:
        raise ValueError("no running steps were recorded")
    return {k: np.concatenate(v) for k, v in cols.items()}, np.concatenate(phase)


def metric_table(measured: dict, bins: int) -> tuple[np.ndarray, list[dict]]:
    """(bin edges: the metric's quantiles, duplicates merged; one row per non-empty bin:
    its range, steps, mean TPA both ways, mean accepted length and whole-acceptance rate)."""
    metric = measured["metric"]
    edges = np.unique(np.quantile(metric, np.linspace(0, 1, bins + 1)))
    which = np.clip(np.searchsorted(edges, metric, side="right") - 1, 0, len(edges) - 2)
    table = [{"metric_lo": float(edges[j]), "metric_hi": float(edges[j + 1]), **_row(measured, which == j)}
             for j in range(len(edges) - 1) if (which == j).any()]
    return edges, table


def group_table(measured: dict, groups: np.ndarray, names: tuple[str, ...]) -> list[dict]:
    """The same row per group (e.g. the expert's phase of each step: groups [N] int indexing
    `names`), for the non-empty groups in `names` order, each with its share of the steps."""
    n = len(groups)
    return [{"group": name, "share": float((groups == g).sum() / n), **_row(measured, groups == g)}
            for g, name in enumerate(names) if (groups == g).any()]


def thresholds(edges: np.ndarray, table: list[dict], hysteresis: float) -> tuple[float, float]:
    """(tau_on, tau_off) from the per-bin table (see the module doc)."""
    loses = [row for row in table if row["tpa_retrieval"] > row["tpa_drafter"]]
    tau_on = loses[0]["metric_lo"] if loses else float(edges[-1])
    tau_on = max(tau_on, float(edges[1]))  # at least the lowest bin goes to retrieval
    return float(tau_on), float(hysteresis * tau_on)


def skip_eps(dist: np.ndarray, accepted: np.ndarray, precision: float, min_steps: int) -> float:
    """The largest nearest-key distance [N] with a whole-acceptance rate of at least
    `precision` among the steps at or below it (and at least `min_steps` of them); 0 if none."""
    n = len(dist)
    order = np.argsort(dist)
    whole_sorted = (accepted[order] == ACTION_DIM).astype(np.float64)
    rate = np.cumsum(whole_sorted) / np.arange(1, n + 1)
    ok = np.flatnonzero((rate >= precision) & (np.arange(1, n + 1) >= min_steps))
    return float(dist[order][ok[-1]]) if len(ok) else 0.0


def calibrate(measured: dict, rule: BoundaryRule, min_dwell: int, about: dict | None = None) -> dict:
    """The boundary.json record: tau_on, tau_off, min_dwell (passed through), skip_eps, the
    per-bin table, the number of steps, `about` (what it was measured on) and the overall
    means."""
    edges, table = metric_table(measured, rule.bins)
    tau_on, tau_off = thresholds(edges, table, rule.hysteresis)
    eps = skip_eps(measured["dist"], measured["accepted"], rule.skip_precision, rule.min_skip_steps)
    return {"tau_on": tau_on, "tau_off": tau_off, "min_dwell": min_dwell, "skip_eps": eps, "table": table,
            "steps": len(measured["metric"]), **(about or {}),
            "overall": {"tpa_retrieval": float(measured["tpa_retrieval"].mean()),
                        "tpa_drafter": float(measured["tpa_drafter"].mean()),
                        "retrieval_whole": float((measured["accepted"] == ACTION_DIM).mean())}}
