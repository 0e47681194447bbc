"""Per-program XLA options: device-side loops for the decode step, determinism for training.

A decode step that runs its draft rounds in a `lax.while_loop` and picks its path with
`lax.cond` returns to the host at every loop test and every branch on a GPU: the predicate is
copied back, and the host launches the next piece. XLA can record loops and conditionals
into the GPU's command buffers (CUDA graphs with conditional nodes) instead, so the whole
step runs as device-side graph nodes (what that saves a host loop: docs/scale.md) -- where
every operation inside them can be recorded: a loop or conditional holding one that cannot (a
cuDNN convolution, in the XLA of jax 0.10-0.11; `vla.Patchify`) stays on the host. Set
process-wide (`XLA_FLAGS=--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL`) it also applies
to the simulator's physics program, which it slows (docs/evaluator.md). `DEVICE_LOOPS` sets it for one program:
`jax.jit(fn, compiler_options=DEVICE_LOOPS)`.

A per-program option replaces XLA's list of command-buffer kinds rather than adding to it
(the `+KIND` syntax is XLA_FLAGS' only), so the list is XLA's default kinds (as of the
XLA in jax 0.10-0.11) and the two loop kinds. The CPU backend ignores it.
"""

from __future__ import annotations

from types import MappingProxyType

# XLA's default command-buffer kinds (debug_options_flags.cc), then the two that keep loops on the device.
COMMAND_BUFFER_KINDS = ("FUSION", "CUBLAS", "CUBLASLT", "CUSTOM_CALL", "CUDNN", "DYNAMIC_SLICE_FUSION",
                        "WHILE", "CONDITIONAL")

DEVICE_LOOPS = MappingProxyType({"xla_gpu_enable_command_buffer": ",".join(COMMAND_BUFFER_KINDS)})

# Run-to-run determinism on a GPU: reductions XLA would do with atomics (the scatter-add of an
# embedding's gradient) and cuDNN's convolution algorithms (the ViT's patch embedding) become
# deterministic ones, so one seed and one dataset give the same parameters on every run of one
# program on one machine (across machines, kernel choices may still differ). Training steps and
# their held-out evaluations are compiled with it unless `TrainConfig.deterministic` is False,
# collections unless `collect_demos --deterministic=false`, and evaluations where
# `EvalConfig.deterministic` (MJX's scatter-adds are atomics on a GPU: without it a rare episode
# ends a step apart between runs). The CPU backend is deterministic anyway.
DETERMINISTIC = MappingProxyType({"xla_gpu_deterministic_ops": True})


def determinism(on: bool) -> dict | None:
    """The compiler options of a program compiled deterministically where `on` (a fresh dict of
    `DETERMINISTIC`, which callers may use as a key), else None (XLA's defaults)."""
    return dict(DETERMINISTIC) if on else None


def parse(text: str) -> dict[str, bool | int | float | str]:
    """`key=value,key=value` as per-program XLA options: true/false become bools and numbers
    numbers (XLA reads each by its field's type), anything else stays text (enum names,
    lists). Raises ValueError on an entry without `=`."""
    out: dict[str, bool | int | float | str] = {}
    for entry in filter(None, (e.strip() for e in text.split(","))):
        key, sep, value = entry.partition("=")
        if not sep or not key:
            raise ValueError(f"XLA option {entry!r} is not key=value (e.g. xla_gpu_deterministic_ops=true)")
        if value.lower() in ("true", "false"):
            out[key] = value.lower() == "true"
            continue
        for kind in (int, float):
            try:
                out[key] = kind(value)
                break
            except ValueError:
                pass
        else:
            out[key] = value
    return out


def check(options) -> None:
    """Compiles a one-element program with `options` on the default backend, so that an option
    the installed XLA does not know, or a value its field cannot take, is refused in one line
    (ValueError) before anything large compiles. Options of another backend's (xla_gpu_* on a
    CPU) are parsed and ignored, as in any program."""
    import jax
    import jax.numpy as jnp
    try:
        jax.jit(lambda x: x + 1, compiler_options=dict(options)).lower(jnp.zeros(1)).compile()
    except Exception as e:  # XLA reports a bad option as a runtime error with its own message
        raise ValueError(f"XLA options {dict(options)} refused: {str(e).splitlines()[0]}") from e
