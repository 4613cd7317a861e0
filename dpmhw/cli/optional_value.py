"""Options whose value may be left out: `--ray` alone means `--ray local`.

Typer has no optional-value option: it deprecated Click's `is_flag=False, flag_value=…` and its
bundled parser always takes the next word as an option's value. A command made with
`optional_values({"--ray": "local"})` fills in the value of a bare `--ray` before the ordinary
parser runs. "Bare" means what it means for Click's optional values and argparse's `nargs="?"`:
last on the command line, or followed by another option. `--ray ADDRESS` and `--ray=ADDRESS`
parse as before. The scan steps over the values of the command's other options, so an option's
value that happens to read `--ray` is left alone.
"""

from __future__ import annotations

import typer
from typer.core import TyperCommand


def optional_values(defaults: dict[str, str]) -> type[TyperCommand]:
    """A Typer command class (`@app.command(cls=…)`) for which each option in `defaults`, given
    without a value, takes the value from `defaults`."""

    class OptionalValueCommand(TyperCommand):
        def parse_args(self, ctx: typer.Context, args: list[str]) -> list[str]:
            return super().parse_args(ctx, fill_bare_options(args, defaults, _value_counts(self.get_params(ctx))))

    return OptionalValueCommand


def _value_counts(params) -> dict[str, int]:
    """How many words follow each option of a command that takes a value (flags take none)."""
    counts = {}
    for param in params:
        if param.param_type_name == "option" and not param.is_flag and not param.count:
            counts.update((opt, param.nargs) for opt in param.opts)
    return counts


def fill_bare_options(args: list[str], defaults: dict[str, str], value_counts: dict[str, int]) -> list[str]:
    """`args` with each bare option of `defaults` written as `OPTION=DEFAULT`."""
    out = list(args)
    i = 0
    while i < len(out):
        word = out[i]
        if word == "--":  # the rest is positional
            break
        if word in defaults:
            following = out[i + 1] if i + 1 < len(out) else None
            if following is None or _is_option(following):
                out[i] = f"{word}={defaults[word]}"
                i += 1
            else:
                i += 2
        else:
            i += 1 + value_counts.get(word, 0)
    return out


def _is_option(word: str) -> bool:
    return word.startswith("-") and len(word) > 1  # the parser's test: "-" alone is a value (stdin)
