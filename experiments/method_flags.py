"""The decoding methods' settings as absl flags, generated from their configs.

Every setting of a VLA method (`heisd_jax.harness.methods.settings`: the settable fields of its
default config) becomes one flag of the same name (`--top_k`, `--budget`, ...), shared by the
methods that have it; its type, valid choices and help come from the setting, and its default
is None: "the chosen method's own default", which the help line lists per method. Sweep keys
(`heisd:top_k=4`) are the same names, checked by `methods.check_settings`; `--preset` (sweep key
`preset`) names a set of them (`methods.PRESETS`).
"""

from __future__ import annotations

from absl import app, flags

from heisd_jax.harness import methods

_DEFINED: dict[int, list[str]] = {}  # per FlagValues object: the flags define() made


def _fmt(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def define(method_names: tuple[str, ...] = methods.DECODING_METHODS,
           flag_values: flags.FlagValues = flags.FLAGS) -> list[str]:
    """Defines one flag per setting of the given methods (once per FlagValues) and
    returns their names (an entry point declares them its key flags, for --helpshort)."""
    if id(flag_values) in _DEFINED:
        return list(_DEFINED[id(flag_values)])
    names = _DEFINED[id(flag_values)] = []
    fields: dict[str, dict] = {}
    for name in method_names:
        for key, s in methods.settings(name).items():
            entry = fields.setdefault(key, {"type": s.kind, "help": s.help, "choices": s.choices, "defaults": {}})
            entry["defaults"][name] = s.default
    for name, e in fields.items():
        defaults = e["defaults"]
        if len({repr(v) for v in defaults.values()}) == 1:
            default = f" (default {_fmt(next(iter(defaults.values())))})"
        else:
            default = " (default " + ", ".join(f"{m} {_fmt(v)}" for m, v in defaults.items()) + ")"
        text = f"{'/'.join(defaults)}: {e['help']}{default}"
        kind = e["type"]
        if e["choices"]:
            flags.DEFINE_enum(name, None, list(e["choices"]), text, flag_values=flag_values)
        elif kind is bool:
            flags.DEFINE_bool(name, None, text, flag_values=flag_values)
        elif kind is int:
            flags.DEFINE_integer(name, None, text, flag_values=flag_values)
        elif kind is float:
            flags.DEFINE_float(name, None, text, flag_values=flag_values)
        else:
            flags.DEFINE_string(name, None, text, flag_values=flag_values)
        names.append(name)
    presets = {m: methods.PRESETS[m] for m in method_names if methods.PRESETS.get(m)}
    if presets:
        choices = sorted({p for named in presets.values() for p in named})
        text = "; ".join(f"{m}'s {p}: " + ",".join(f"{k}={_fmt(v)}" for k, v in named[p].items())
                         for m, named in presets.items() for p in named)
        flags.DEFINE_enum(methods.PRESET, None, choices, f"A named set of settings, which settings given beside it "
                          f"replace (the 7B scale's measured configuration per batch size, docs/scale.md): {text}.",
                          flag_values=flag_values)
        names.append(methods.PRESET)
    return list(names)


def given(method: str, flag_values: flags.FlagValues = flags.FLAGS) -> dict:
    """The settings of `method` given on the command line, typed and checked (an
    `app.UsageError` naming the problem, before anything loads or compiles)."""
    names = _DEFINED.get(id(flag_values), [])
    values = {name: flag_values[name].value for name in names if flag_values[name].value is not None}
    try:
        valid = (set(methods.settings(method)) | ({methods.PRESET} if methods.PRESETS.get(method) else set())) \
            & set(names)
        extra = [name for name in values if name not in valid]
        if extra:
            raise ValueError(f"--method={method} takes none of --{', --'.join(extra)}")
        return methods.check_settings(method, values)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
