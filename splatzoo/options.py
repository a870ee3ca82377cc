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
    Values stay strings: make_config converts and checks them. A key given twice (hidden=1,hidden=2, or n_waves and
    n-waves) is an error: no value is silently dropped. Export formats (ply:viewer=3dgs) use the same syntax."""
    from .errors import SplatzooError

    name, _, rest = text.partition(":")
    options, given = {}, {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq:
            raise SplatzooError(f"option {item!r} in {text!r} must look like key=value")
        name_key = key.strip().lstrip("-").replace("-", "_")
        if not name_key:
            raise SplatzooError(f"option {item!r} in {text!r} has no name before '='; write key=value")
        if name_key in options:
            raise SplatzooError(f"option {name_key} is given twice in {text!r} ({given[name_key]!r} and "
                                f"{item.strip()!r}); give it once")
        options[name_key] = value.strip()
        given[name_key] = item.strip()
    return name.strip(), options


def merge_options(inline: dict, flags: dict, model: str) -> dict:
    """The options written inline (gabor:n_waves=8) and as flags (--n-waves 8) together; one option in both places
    is an error rather than a silent choice of one of them."""
    both = [k for k in flags if k in inline]
    if both:
        said = ", ".join(f"{k} ({inline[k]!r} inline, {flags[k]!r} as --{k.replace('_', '-')})" for k in both)
        raise ModelOptionError(f"model {model!r}: option(s) given twice, {said}; give each once")
    return {**inline, **flags}


def parse_model_args(model: str, args: list[str], positionals: list | None = None) -> dict:
    """['--n-waves', '8', '--flag', '--no-other'] -> {'n_waves': '8', 'flag': True, 'other': False}.
    Values stay strings: make_config converts and checks them. Unset options are absent (keep defaults). An option
    given twice (--n-waves 2 --n-waves 4, --flag --no-flag) is an error. A word that is no option nor an option's
    value goes to `positionals` when it is given (a command's own argument typed after the model options), else it
    is an error."""
    from .zoo import get_model_spec

    spec = get_model_spec(model)
    fields = {flag: (typ, name) for (flag, typ, _, _), name in
              zip(option_fields(spec.config_cls), [f.name for f in dataclasses.fields(spec.config_cls)])}
    known = ", ".join(fields) or "none"
    out, said, i = {}, {}, 0

    def put(name: str, value, text: str) -> None:
        if name in out:
            raise ModelOptionError(f"option --{name.replace('_', '-')} of model {model!r} is given twice "
                                   f"({said[name]!r} and {text!r}); give it once")
        out[name], said[name] = value, text

    while i < len(args):
        arg = args[i]
        flag, eq, value = arg.partition("=")
        negated = flag.startswith("--no-") and ("--" + flag[5:]) in fields and fields["--" + flag[5:]][0] is bool
        if negated:
            put(fields["--" + flag[5:]][1], False, arg)
            i += 1
            continue
        if not arg.startswith("-") and positionals is not None:
            positionals.append(arg)
            i += 1
            continue
        if not arg.startswith("-"):
            raise ModelOptionError(f"unexpected argument {arg!r}: model options are flags such as "
                                   f"{next(iter(fields), '--name')} VALUE (model {model!r} takes: {known})")
        if flag not in fields:
            from .registry import closest

            raise ModelOptionError(f"unknown option {flag!r} for model {model!r}; its options: {known}"
                                   + closest(flag, list(fields)))
        typ, name = fields[flag]
        if typ is bool and not eq:
            put(name, True, arg)
            i += 1
            continue
        if not eq:
            if i + 1 >= len(args):
                raise ModelOptionError(f"option {flag} of model {model!r} needs a value")
            value = args[i + 1]
            arg = f"{flag} {value}"
            i += 1
        put(name, value, arg)
        i += 1
    return out


def describe_options(model: str) -> str:
    from .zoo import get_model_spec

    spec = get_model_spec(model)
    rows = [f"  {flag} {typ.__name__.upper()}  {hlp} (default {default})"
            for flag, typ, default, hlp in option_fields(spec.config_cls)]
    return "\n".join(rows) if rows else "  (no options)"
