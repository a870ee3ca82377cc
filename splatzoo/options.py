"""Model options on the command line, derived from each model's config dataclass (n_waves -> --n-waves)."""
from __future__ import annotations

import dataclasses
import typing

from .models.base import ModelOptionError


def option_fields(config_cls) -> list[tuple[str, type, object, str]]:
    """(flag, type, default, help) for every field of a model config."""
    hints = typing.get_type_hints(config_cls)
    out = []
    for f in dataclasses.fields(config_cls):
        default = f.default if f.default is not dataclasses.MISSING else None
        out.append(("--" + f.name.replace("_", "-"), hints.get(f.name, str), default, f.metadata.get("help", "")))
    return out


def model_spec(text: str) -> tuple[str, dict]:
    """A model with its options in one word, the syntax every command accepts:
    'gabor' or 'gabor:n_waves=8,prune_waves=0.01' (or n-waves=8) -> ('gabor', {'n_waves': '8', ...}).
    Values stay strings: make_config converts and checks them."""
    from .errors import SplatzooError

    name, _, rest = text.partition(":")
    options = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq:
            raise SplatzooError(f"model option {item!r} in {text!r} must look like key=value")
        options[key.strip().lstrip("-").replace("-", "_")] = value.strip()
    return name.strip(), options


def parse_model_args(model: str, args: list[str]) -> dict:
    """['--n-waves', '8', '--flag', '--no-other'] -> {'n_waves': '8', 'flag': True, 'other': False}.
    Values stay strings: make_config converts and checks them. Unset options are absent (keep defaults)."""
    from .zoo import get_model_spec

    spec = get_model_spec(model)
    fields = {flag: (typ, name) for (flag, typ, _, _), name in
              zip(option_fields(spec.config_cls), [f.name for f in dataclasses.fields(spec.config_cls)])}
    known = ", ".join(fields) or "none"
    out, i = {}, 0
    while i < len(args):
        arg = args[i]
        flag, eq, value = arg.partition("=")
        negated = flag.startswith("--no-") and ("--" + flag[5:]) in fields and fields["--" + flag[5:]][0] is bool
        if negated:
            out[fields["--" + flag[5:]][1]] = False
            i += 1
            continue
        if flag not in fields:
            from .registry import closest

            raise ModelOptionError(f"unknown option {flag!r} for model {model!r}; its options: {known}"
                                   + closest(flag, list(fields)))
        typ, name = fields[flag]
        if typ is bool and not eq:
            out[name] = True
            i += 1
            continue
        if not eq:
            if i + 1 >= len(args):
                raise ModelOptionError(f"option {flag} of model {model!r} needs a value")
            value = args[i + 1]
            i += 1
        out[name] = value
        i += 1
    return out


def describe_options(model: str) -> str:
    from .zoo import get_model_spec

    spec = get_model_spec(model)
    rows = [f"  {flag} {typ.__name__.upper()}  {hlp} (default {default})"
            for flag, typ, default, hlp in option_fields(spec.config_cls)]
    return "\n".join(rows) if rows else "  (no options)"
