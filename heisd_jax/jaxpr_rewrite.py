"""Re-evaluates a function's program with some primitives replaced, nested programs included.

`with_rules(fn, rules)` traces fn to a jaxpr and evaluates it equation by equation, binding
each into the caller's trace, except where `rules` names the equation's primitive: there the
rule computes its outputs from its inputs and parameters. Programs held by parameters (a
scan's body, a while loop's condition and body, a conditional's branches, a checkpoint's or
a custom derivative's call) are rewritten alike, so a model needs no change to have, say,
every matrix product rounded (`rounded_products`) or run by another kernel
(`invariant_products`).
"""

from __future__ import annotations

import functools
from typing import Callable, Mapping

import jax
import jax.extend.core as jcore
import numpy as np

# A rule: (input values, the equation's parameters) -> its output value, or list of values
# for a primitive with several results.
Rule = Callable[..., object]


def evaluate(jaxpr: jcore.Jaxpr, consts, args, rules: Mapping[str, Rule]):
    """jaxpr's outputs on args, each equation bound into the caller's trace or, where its
    primitive is in rules, computed by the rule; nested programs rewritten by the same rules."""
    env = {}

    def read(v):
        return v.val if isinstance(v, jcore.Literal) else env[v]

    for v, x in zip(jaxpr.constvars, consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, args):
        env[v] = x
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        rule = rules.get(eqn.primitive.name)
        if rule is not None:
            outs = rule(invals, **eqn.params)
        else:
            params = {k: _rewrite_param(v, rules) for k, v in eqn.params.items()}
            outs = eqn.primitive.bind(*invals, **params)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, x in zip(eqn.outvars, outs):
            if not isinstance(v, jcore.DropVar):
                env[v] = x
    return [read(v) for v in jaxpr.outvars]


def _rewrite_closed(closed: jcore.ClosedJaxpr, rules) -> jcore.ClosedJaxpr:
    """The same program rewritten by rules, with the same signature."""
    avals = [v.aval for v in closed.jaxpr.invars]
    new = jax.make_jaxpr(lambda *a: evaluate(closed.jaxpr, closed.consts, a, rules))(*avals)
    if [v.aval for v in new.jaxpr.invars] != avals or new.out_avals != closed.out_avals:
        raise TypeError("rewriting a sub-program changed its signature")  # a bug in a rule, not the caller's
    return new


def _rewrite_param(value, rules):
    """A primitive's parameter with the programs it holds rewritten alike; anything else unchanged."""
    if isinstance(value, jcore.ClosedJaxpr):
        return _rewrite_closed(value, rules)
    if isinstance(value, jcore.Jaxpr):  # an open program (a checkpoint's): no constants of its own
        new = _rewrite_closed(jcore.ClosedJaxpr(value, ()), rules)
        if new.consts:
            raise NotImplementedError("rewriting an open sub-program made constants")
        return new.jaxpr
    if isinstance(value, tuple) and value and all(isinstance(v, jcore.ClosedJaxpr) for v in value):
        return tuple(_rewrite_closed(v, rules) for v in value)
    return value


def with_rules(fn, rules: Mapping[str, Rule]):
    """fn evaluated with the primitives named in rules computed by them (`evaluate`).
    Arguments that are not arrays (configs) pass through as static values; the result has
    fn's structure."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        leaves, tree = jax.tree.flatten((args, kwargs))
        is_array = [isinstance(x, (jax.Array, np.ndarray, np.generic)) for x in leaves]
        arrays = [x for x, a in zip(leaves, is_array) if a]

        def flat_fn(*xs):
            it = iter(xs)
            a, k = jax.tree.unflatten(tree, [next(it) if arr else x for x, arr in zip(leaves, is_array)])
            return fn(*a, **k)

        closed, out_shape = jax.make_jaxpr(flat_fn, return_shape=True)(*arrays)
        outs = evaluate(closed.jaxpr, closed.consts, arrays, rules)
        return jax.tree.unflatten(jax.tree.structure(out_shape), outs)

    return wrapped
