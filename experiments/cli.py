"""How every entry point starts: absl flags, and a user's mistake answered in one line.

`run(main)` replaces `absl.app.run(main)`. A flag that does not parse or fails its validator,
and an `app.UsageError` raised by `main` while it checks its inputs (before anything
expensive starts), end the program with one line on stderr naming the problem and exit
status 2: no traceback, no usage text (`--helpshort` still prints the flags).
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
from typing import Callable, NoReturn

from absl import app, flags

USAGE_EXIT = 2


def _prog() -> str:
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None and spec.name:
        return f"python -m {spec.name}"
    return os.path.basename(sys.argv[0]) if sys.argv else "heisd-jax"


def fail(message: str) -> NoReturn:
    """Ends the program with one error line (the problem and the valid choices)."""
    first, *rest = str(message).strip().splitlines() or ["invalid input"]
    text = " ".join([first, *(line.strip() for line in rest)])
    sys.stderr.write(f"{_prog()}: error: {text}\n")
    sys.exit(USAGE_EXIT)


def _parse_flags(argv: list[str]) -> list[str]:
    try:
        return flags.FLAGS(argv)
    except flags.Error as e:
        fail(f"{e} (--helpshort lists the flags)")


def run(main: Callable[[list[str]], object]) -> None:
    """`absl.app.run(main)`, with bad flags and `app.UsageError` reported in one line."""

    def checked_main(argv: list[str]):
        try:
            return main(argv)
        except app.UsageError as e:
            fail(str(e))

    app.run(checked_main, flags_parser=_parse_flags)


def positive_int_list(flag_name: str) -> None:
    """Validates a DEFINE_list flag as comma-separated positive integers when flags parse."""
    flags.register_validator(
        flag_name, lambda values: all(str(v).strip().isdigit() and int(v) > 0 for v in values),
        message="expected comma-separated positive integers")


def existing_dir(flag_name: str, what: str) -> None:
    """Validates a path flag when flags parse: empty (none) or an existing directory."""

    def check(value: str) -> bool:
        if value and not Path(value).is_dir():
            raise flags.ValidationError(f"no {what} there")
        return True

    flags.register_validator(flag_name, check)


def define_calibrate_costs() -> None:
    """--calibrate_costs, for the entry points that build methods with budget=auto."""
    if "calibrate_costs" in flags.FLAGS:
        return
    flags.DEFINE_bool("calibrate_costs", False, "budget=auto: where no decode-cost table is cached for this device, "
                      "model, settings and batch size, measure it now (1-3 min, then cached) instead of failing.")
