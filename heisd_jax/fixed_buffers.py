"""A step called from a host loop whose inputs, carried state and results stay at fixed
device addresses from call to call.

On a GPU XLA runs a program's kernels as CUDA graphs (command buffers). Before each call it
compares the addresses of the buffers the graph reads and writes with the last call's, and
re-records the graph's commands that touch a buffer that moved (`command_buffer::update`),
which the next graph launch then uploads. A control loop that calls the decode step once per
control step hands it new observation and state buffers and gets new result buffers on every
call, so every call may pay that update for graphs of ~1,000 commands at a 7B target's size
(docs/scale.md: how much of a call's time it is, `experiments/profile.py --fixed_buffers`
measures).

`FixedBufferStep` keeps the step's inputs, its carried state and its results in one set of
device buffers ("slots"). Every call donates the slots and aliases them to the outputs, so a
buffer keeps its address: a small program copies the call's new inputs (those the step reads:
a simulator state's other fields are left out) into the input slots, then the step reads the
slots and writes its carried state and results back into them. The large program then sees the same argument and result addresses on every call; its temporary
buffer may still move between calls, unless XLA is told to keep it fixed
(`xla_gpu_command_buffer_update_mode=SKIP_TEMP`).

It computes what `fn` computes. The results it returns live in the slots: they are valid
until the next call, which reuses their buffers (copy what must outlive it). A buffer that
something outside JAX still views at the next call (on CPU, `np.asarray` of a result is such
a view) is not reused: JAX copies instead, the values stay right, and that slot moves.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.extend.core as jcore
import jax.numpy as jnp

Step = Callable[[Any, Any, Any], tuple[Any, Any]]  # fn(params, inputs, carry) -> (results, carry)


def read_inputs(closed: jcore.ClosedJaxpr) -> list[bool]:
    """Which of a traced program's inputs it reads: an equation counts as reading all its
    operands if anything reads one of its results or it has effects (a loop's or a branch's
    body counts whole, so the answer may say more is read than is, never less)."""
    jaxpr = closed.jaxpr
    live = {v for v in jaxpr.outvars if isinstance(v, jcore.Var)}
    for eqn in reversed(jaxpr.eqns):
        if eqn.effects or any(v in live for v in eqn.outvars if not isinstance(v, jcore.DropVar)):
            live.update(v for v in eqn.invars if isinstance(v, jcore.Var))
    return [v in live for v in jaxpr.invars]


def _put(slots, inputs):
    # The barrier makes each input an op's result, which XLA then writes into the donated slot
    # (a result that is a bare argument would be forwarded as that argument's own buffer).
    return jax.lax.optimization_barrier(inputs), slots[1], slots[2]


class FixedBufferStep:
    """`fn(params, inputs, carry) -> (results, carry)` called on fixed device buffers.

    `inputs` and `carry` are examples (any pytrees of arrays) that fix the shapes every call
    must keep, and `carry` is the state the first call starts from. `jit` compiles the step
    (e.g. `functools.partial(jax.jit, compiler_options=...)`); it is called with
    `donate_argnums` and `keep_unused`. `params` stay where they are: they do not move between
    calls anyway."""

    def __init__(self, fn: Step, params, inputs, carry, jit=jax.jit):
        closed, shapes = jax.make_jaxpr(fn, return_shape=True)(params, inputs, carry)
        leaves = jax.tree.leaves(inputs)
        n_params = len(jax.tree.leaves(params))
        # Only the inputs the step reads get a slot and are copied per call; the others are
        # zeros inside the program, which XLA drops.
        self._read = read_inputs(closed)[n_params:n_params + len(leaves)]
        self.params = params
        self._structure = jax.tree.structure(inputs)
        self._avals = [(x.shape, x.dtype) for x in leaves]
        self._slots = ([jnp.copy(x) for x, r in zip(leaves, self._read) if r], jax.tree.map(jnp.copy, carry),
                       jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes[0]))

        def run(params, slots):
            read, carry, _ = slots
            it = iter(read)
            leaves = [next(it) if r else jnp.zeros(*a) for r, a in zip(self._read, self._avals)]
            results, carry = fn(params, jax.tree.unflatten(self._structure, leaves), carry)
            return read, carry, results

        # keep_unused: an argument jit would otherwise drop (the last call's results, an input
        # the step does not read) is still donated and so keeps its buffer as an output.
        self._put = jax.jit(_put, donate_argnums=0, keep_unused=True)
        self._run = jit(run, donate_argnums=1, keep_unused=True)
        self._set_carry = None

    def __call__(self, inputs):
        """Runs the step on `inputs` (arrays in the example's structure, shapes and dtypes);
        returns its results, which live in the slots until the next call."""
        leaves, structure = jax.tree.flatten(inputs)  # once: this runs at every control step
        if structure != self._structure:
            raise ValueError(f"inputs have structure {structure}, the step was built for {self._structure}")
        avals = [(x.shape, x.dtype) for x in leaves]
        if avals != self._avals:
            bad = next(i for i, (a, b) in enumerate(zip(avals, self._avals)) if a != b)
            raise ValueError(f"input leaf {bad} has shape and dtype {avals[bad]}, the step was built for "
                             f"{self._avals[bad]}")
        read = [x for x, r in zip(leaves, self._read) if r]
        self._slots = self._run(self.params, self._put(self._slots, read))
        return self._slots[2]

    def reset(self, carry) -> None:
        """Starts the next call from `carry` (the example's structure), in the same buffers."""
        if self._set_carry is None:
            self._set_carry = jax.jit(lambda slots, carry: (slots[0], jax.lax.optimization_barrier(carry), slots[2]),
                                      donate_argnums=0, keep_unused=True)
        self._slots = self._set_carry(self._slots, carry)

    @property
    def carry(self):
        """The carried state after the last call (in the slots: valid until the next call)."""
        return self._slots[1]

    def buffer_addresses(self) -> list[int]:
        """The device address of every slot's buffer (tests and diagnostics)."""
        return [x.unsafe_buffer_pointer() for x in jax.tree.leaves(self._slots)]
