"""The decoding methods' settings as absl flags, generated from their settings records.

Every field of a VLA method's settings dataclass (`heisd_jax.methods.Method.settings`)
becomes one flag of the same name (`--top_k`, `--budget`, ...), shared by the methods that
have the field; its type, valid choices and help come from the field, and its default is
None: "the chosen method's own default", which the help line lists per method. Sweep keys
(`heisd:top_k=4`) are the same field names, checked by `methods.check_settings`.
"""

from __future__ import annotations

import dataclasses

from absl import app, flags

from heisd_jax import methods

_DEFINED: dict[int, list[str]] = {}  # per FlagValues object: the flags define() made


def _fmt(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def define(method_names: tuple[str, ...] = methods.DECODING_METHODS,
           flag_values: flags.FlagValues = flags.FLAGS) -> list[str]:
    """Defines one flag per settings field of the given methods (once per FlagValues) and
    returns their names (an entry point declares them its key flags, for --helpshort)."""
    if id(flag_values) in _DEFINED:
        return list(_DEFINED[id(flag_values)])
    names = _DEFINED[id(flag_values)] = []
    fields: dict[str, dict] = {}
    for name in method_names:
        cls = methods.get(name).settings
        types = methods.setting_types(cls)
        for f in dataclasses.fields(cls):
            entry = fields.setdefault(f.name, {"type": types[f.name], "help": f.metadata.get("help", ""),
                                               "choices": f.metadata.get("choices"), "defaults": {}})
            entry["defaults"][name] = f.default
    for name, e in fields.items():
        defaults = e["defaults"]
        if all(v is None or v == "" for v in defaults.values()):  # the help line says what applies
            default = ""
        elif len({repr(v) for v in defaults.values()}) == 1:
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
    return list(names)


def given(method: str, flag_values: flags.FlagValues = flags.FLAGS) -> dict:
    """The settings of `method` given on the command line, typed and checked (an
    `app.UsageError` naming the problem, before anything loads or compiles)."""
    names = _DEFINED.get(id(flag_values), [])
    values = {name: flag_values[name].value for name in names if flag_values[name].value is not None}
    try:
        valid = {f.name for f in dataclasses.fields(methods.get(method).settings)} & set(names)
        extra = [name for name in values if name not in valid]
        if extra:
            raise ValueError(f"--method={method} takes none of --{', --'.join(extra)}")
        return methods.check_settings(method, values)
    except ValueError as e:
        raise app.UsageError(str(e)) from e
