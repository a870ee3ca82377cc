"""Options: a model's on the command line, derived from its config dataclass (n_waves -> --n-waves), the one-word
syntax every command takes (gabor:n_waves=8, baked:max_splats=16000), and the one coercer that turns an option's
value (a string from a command line or a header, or a typed value) into its field's type, for model configs, export
formats, mesh texture and bake options alike."""
from __future__ import annotations

import dataclasses
import math
import types
import typing

from .errors import SplatzooError
from .models.base import ModelOptionError

BOOL_WORDS = {"true": True, "1": True, "yes": True, "on": True, "false": False, "0": False, "no": False, "off": False}
NONE_WORDS = ("none", "null", "auto", "default", "")  # an optional field's "unset", as a word


def option_value(what: str, key: str, typ, value, default=None, *, error=SplatzooError):
    """The option `key` of `what` ("model 'gabor'", "export format 'spz'", "mesh texture", "bake") converted to its
    field's type `typ`; anything it cannot be is an `error` saying "{what}: option {key} expects {type}, got {value}".
    Options often arrive as strings (command line, PLY headers), and bool("False") is True, so bools are parsed by
    their words rather than cast; a count never takes a fraction or a bool; a float must be finite (but for a field's
    own non-finite `default`, which a config hands back through its dict); an optional field (X | None) takes None
    or one of NONE_WORDS for "unset". Other types pass through: the options class checks them."""
    def bad(expected: str):
        return error(f"{what}: option {key} expects {expected}, got {value!r}")

    if typing.get_origin(typ) in (typing.Union, types.UnionType) and type(None) in typing.get_args(typ):
        inner = [t for t in typing.get_args(typ) if t is not type(None)]
        if value is None or (isinstance(value, str) and value.strip().lower() in NONE_WORDS):
            return None
        if len(inner) != 1:
            return value
        typ = inner[0]
    if typ is bool:
        if isinstance(value, bool):
            return value
        if type(value) is int and value in (0, 1):
            return bool(value)
        if isinstance(value, str) and value.strip().lower() in BOOL_WORDS:
            return BOOL_WORDS[value.strip().lower()]
        raise bad("bool (true/false, yes/no, on/off or 1/0)")
    if typ in (int, float):
        if isinstance(value, bool):  # a bool is an int to Python, but never a count or a rate
            raise bad(typ.__name__)
        try:
            if typ is float:
                converted = float(value)
            elif isinstance(value, float):
                if not value.is_integer():
                    raise ValueError  # int() would silently drop the fraction
                converted = int(value)
            else:
                converted = int(value)
        except (TypeError, ValueError, OverflowError):
            raise bad(typ.__name__) from None
        if typ is float and not math.isfinite(converted) and not (isinstance(value, float) and value == default):
            raise bad("a finite float")
        return converted
    if typ is str:
        return str(value)
    return value


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
    from .registry import MODELS

    spec = MODELS.get(model)
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
    from .registry import MODELS

    spec = MODELS.get(model)
    rows = [f"  {flag} {typ.__name__.upper()}  {hlp} (default {default})"
            for flag, typ, default, hlp in option_fields(spec.config_cls)]
    return "\n".join(rows) if rows else "  (no options)"
