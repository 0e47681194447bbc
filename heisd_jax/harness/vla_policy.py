"""VLA decoding methods as batched rollout policies (`envs.rollout.Policy`).

A decoding method is a pure function `decode(params, cfg, obs) -> (tokens [B, 7], stats)`
over a batch of observations; `stats` holds per-row numbers for this action (at least
`target_passes`). `decoding_policy` turns one into a policy: observation from the env
state, decode, detokenize. The checkpoint's parameters ride in `Policy.params`, so the
jitted rollout takes them as an argument.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import jax.numpy as jnp

from envs.env import EnvState
from envs.rollout import Policy, Stats
from heisd_jax import hybrid, spec_decode, target_model, vla
from heisd_jax.tokenizer import INVALID_ID, ActionTokenizer

DEFAULT_CHECKPOINT = Path(__file__).resolve().parents[2] / "checkpoints" / "vla"
DEFAULT_DRAFTER = Path(__file__).resolve().parents[2] / "checkpoints" / "drafter"
DEFAULT_DATASTORE = Path(__file__).resolve().parents[2] / "checkpoints" / "datastore"

DecodeFn = Callable[[dict, vla.VLAConfig, vla.Observation], tuple[jnp.ndarray, Stats]]


def observation(states: EnvState) -> vla.Observation:
    """The VLA's inputs from a batch of env states (the env's observation, field for field)."""
    o = states.obs
    return vla.Observation(image=o.image, instruction=o.instruction, proprio=o.proprio)


def decoding_policy(name: str, params, cfg: vla.VLAConfig, tok: ActionTokenizer, decode: DecodeFn,
                    **meta) -> Policy:
    def act(params, states, pstate, keys):
        obs = observation(states)
        tokens, stats = vla.mark_invalid(cfg, obs, *decode(params, cfg, obs))
        return tok.to_actions(tokens), pstate, stats

    return Policy(name=name, init=lambda params, states: (), act=act, params=params, meta=dict(cfg=cfg, tok=tok, **meta))


def ar(params, cfg: vla.VLAConfig, obs: vla.Observation) -> tuple[jnp.ndarray, Stats]:
    """Greedy autoregressive decoding (the baseline): 7 target passes per action."""
    return target_model.ar_action(params, cfg, obs)


def drafter_sd(spec):
    """Drafter-based speculative decoding (Spec-VLA / EAGLE-2) with the given drafter
    parameters and `spec_decode.SpecConfig`, as a DecodeFn over (target params, ...)."""
    def decode(params, cfg, obs):
        return spec_decode.spec_decode(params["target"], params["drafter"], cfg, spec, obs)
    return decode


def hybrid_policy(name: str, params, cfg: vla.VLAConfig, tok: ActionTokenizer, hcfg, key_spec,
                  global_task_index) -> Policy:
    """The HeiSD step (`heisd_jax.hybrid`) as a policy. params: {"target", "drafter",
    "store"} (+ "costs" for budget "auto"); global_task_index [n_tasks]: the datastore's task index of each env task."""
    gidx = jnp.asarray(global_task_index, jnp.int32)

    def init(params, states):
        return hybrid.init_state(states.step.shape[0], key_spec, hcfg)

    def act(params, states, pstate, keys):
        kin = hybrid.Kinematics(lin_vel=states.kin.lin_vel, ang_vel=states.kin.ang_vel, lin_acc=states.kin.lin_acc,
                                gripper_vel=states.kin.gripper_vel)
        obs = observation(states)
        actions, tokens, pstate, stats = hybrid.step(params, cfg, hcfg, key_spec, tok, pstate, obs, kin,
                                                     gidx[states.info.task_id])
        tokens, stats = vla.mark_invalid(cfg, obs, tokens, stats)
        return jnp.where((tokens == INVALID_ID)[:, :1], tok.to_actions(tokens), actions), pstate, stats

    return Policy(name=name, init=init, act=act, params=params,
                  meta=dict(cfg=cfg, tok=tok, hcfg=hcfg, spec=hcfg.spec, key_spec=key_spec))
