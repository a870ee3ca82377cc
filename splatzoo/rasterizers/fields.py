"""The native rasterizer's view of the Surfels field table: csrc/surfel_fields.h, generated from the declarations in
splatzoo/types.py so that a per-surfel field is declared once.

`python -m splatzoo.rasterizers.fields` rewrites the header after a field was added or changed (tests check that the
shipped header is current, and the native backend refuses a build whose fields differ from the table).
"""
from __future__ import annotations

import sys
from pathlib import Path

import re

from ..types import BUILTIN_KINDS, SURFEL_FIELDS, SURFEL_ROLES

HEADER = Path(__file__).resolve().parents[1] / "csrc" / "surfel_fields.h"
MAX_RANK = 3  # trailing dimensions a field may have


def pair_fields() -> list[str]:
    """The fields the tile loops read for every (surfel, pixel) pair: every role but geometry."""
    return [f.name for f in SURFEL_FIELDS if f.role != "geometry"]


def kind_struct(kind: str) -> str:
    """The C++ struct of appearance kind `kind` (snake_case in the table): its CamelCase, e.g. WaveBank."""
    if not re.fullmatch(r"[a-z][a-z0-9]*(_[a-z0-9]+)*", kind):
        raise ValueError(f"appearance kind {kind!r}: name kinds in snake_case (its C++ struct is the CamelCase)")
    return "".join(w.capitalize() for w in kind.split("_"))


def kind_fields(kind: str) -> list:
    """The fields of appearance kind `kind`, in table order."""
    return [f for f in SURFEL_FIELDS if f.kind == kind]


def row_size(dims) -> str:
    """A field's scalars per surfel as a C++ expression of the batch's K and T."""
    return " * ".join(str(d) for d in dims) or "1"


def kind_lists() -> str:
    """The generated part of each kind's struct: its fields' pointer list, and the list of kinds."""
    lines = []
    for kind in BUILTIN_KINDS:
        rows = " ".join(f"X({f.name}, {row_size(f.dims)})" for f in kind_fields(kind))
        lines.append(f"#define SZ_KIND_FIELDS_{kind.upper()}(X) {rows}")
    kinds = " ".join(f"X({kind_struct(k)}, {k}, SZ_KIND_FIELDS_{k.upper()})" for k in BUILTIN_KINDS)
    lines.append(f"#define SZ_APPEARANCE_KINDS(X) {kinds}")
    return "\n".join(lines)


def header_text() -> str:
    """csrc/surfel_fields.h for the current table."""
    rows = []
    for f in SURFEL_FIELDS:
        if len(f.dims) > MAX_RANK:
            raise ValueError(f"Surfels.{f.name} has {len(f.dims)} trailing dimensions; at most {MAX_RANK}")
        dims = [{"K": "SZ_K", "T": "SZ_T"}.get(d) or str(int(d)) for d in f.dims] + ["0"] * (MAX_RANK - len(f.dims))
        rows.append(f'    {{"{f.name}", Role::{f.role}, {len(f.dims)}, {{{", ".join(dims)}}}}},  // {f.doc}')
    names = " ".join(f"X({f.name})" for f in SURFEL_FIELDS)
    pair = " ".join(f"X({n})" for n in pair_fields())
    roles = ", ".join(SURFEL_ROLES)
    return f"""// Generated from the Surfels field table (splatzoo/types.py) by `python -m splatzoo.rasterizers.fields`: do
// not edit. Every per-surfel field, in table order (the order render() takes them in); the bindings (ext.cpp) derive
// their checks, arguments and gradient buffers from it, and the tile loops' argument structs (rasterize.h) their
// per-pair pointers.
#pragma once

namespace sz {{

enum class Role {{ {roles} }};
constexpr int SZ_K = -1;  // a dimension equal to the batch's wave count K
constexpr int SZ_T = -2;  // a dimension equal to the batch's texture size T (texels a side)

struct SurfelFieldInfo {{
    const char* name;
    Role role;
    int rank;  // trailing dimensions after N
    int dims[{MAX_RANK}];  // SZ_K: K, SZ_T: T
}};

constexpr int NUM_SURFEL_FIELDS = {len(SURFEL_FIELDS)};
constexpr SurfelFieldInfo SURFEL_FIELD_INFO[NUM_SURFEL_FIELDS] = {{
{chr(10).join(rows)}
}};

}}  // namespace sz

// X(name) for every field, in table order
#define SZ_SURFEL_FIELDS(X) {names}
// X(name) for the fields the tile loops read per (surfel, pixel) pair (every role but geometry)
#define SZ_PAIR_FIELDS(X) {pair}
// X(name, row) for the fields of each appearance kind, in table order; row: the field's scalars per surfel, in terms
// of the batch's sizes K and T (names the expansion site defines). Each kind's struct (surfel_math.h) declares its
// field pointers and gradient pointers from its list.
{kind_lists()}
"""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = header_text()
    if argv == ["--check"]:
        current = HEADER.read_text() if HEADER.is_file() else ""
        if current != text:
            print(f"{HEADER} is out of date with the Surfels field table; run python -m splatzoo.rasterizers.fields",
                  file=sys.stderr)
            return 1
        return 0
    if argv:
        print("usage: python -m splatzoo.rasterizers.fields [--check]", file=sys.stderr)
        return 2
    tmp = HEADER.with_suffix(".h.tmp")
    tmp.write_text(text)
    tmp.replace(HEADER)
    print(f"wrote {HEADER}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
