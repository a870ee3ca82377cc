"""Appearance kinds as units: each kind of the Surfels table has one section of csrc/surfel_math.h, its rows in the
table and its twin in rasterizers/reference.py, and nothing else names it."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from splatzoo.rasterizers import fields as field_header
from splatzoo.rasterizers.reference import KIND_TWINS
from splatzoo.types import BUILTIN_KINDS, SURFEL_FIELDS, surfel_field

CSRC = Path(__file__).resolve().parents[1] / "splatzoo" / "csrc"


def _code(path: Path) -> str:
    """A C++ source without its comments and string literals (what the code itself names)."""
    text = path.read_text()
    text = re.sub(r"//[^\n]*", "", text)
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r'"(\\.|[^"\\])*"', '""', text)


# ---- kinds as units -------------------------------------------------------------------------------------------------

def test_every_kind_of_the_table_has_its_header_section_and_its_twin():
    header = (CSRC / "surfel_math.h").read_text()
    assert BUILTIN_KINDS == ("wave_bank", "texture")
    assert tuple(KIND_TWINS) == BUILTIN_KINDS, "every kind of the table has its twin in reference.KIND_TWINS"
    for kind in BUILTIN_KINDS:
        struct = field_header.kind_struct(kind)
        section = rf"\nstruct {struct} {{\n    SZ_KIND_FIELD_MEMBERS\(SZ_KIND_FIELDS_{kind.upper()}\)"
        assert re.search(section, header), (
            f"csrc/surfel_math.h has no section for the kind {kind!r} (struct {struct} over its generated fields)")
        # its section holds every member the composition calls
        body = header[header.index(f"struct {struct} {{"):]
        body = body[:body.index("\n};\n")]
        for member in ("dense_slots", "scatter_slots", "prepared_width", "fold_values", "fold_factors", "has_gain",
                       "gain(", "bind(", "prepare(", "fold(", "unfold(", "add_colour(", "backward(", "finalize(",
                       "struct Cache"):
            assert member in body, f"{struct} declares no {member}"


def test_the_generator_emits_each_kinds_fields_and_the_kind_list():
    text = field_header.header_text()
    assert "#define SZ_KIND_FIELDS_WAVE_BANK(X) X(base_color, 3) X(wave_vectors, K * 2) X(wave_phases, K) " \
           "X(wave_amplitudes, K * 3)" in text
    assert "#define SZ_KIND_FIELDS_TEXTURE(X) X(texture, T * T * 4)" in text
    assert "#define SZ_APPEARANCE_KINDS(X) X(WaveBank, wave_bank, SZ_KIND_FIELDS_WAVE_BANK) X(Texture, texture, " \
           "SZ_KIND_FIELDS_TEXTURE)" in text
    for f in SURFEL_FIELDS:
        assert (f.kind is not None) == (f.role == "appearance"), f.name
    assert field_header.kind_struct("wave_bank") == "WaveBank"
    with pytest.raises(ValueError, match="snake_case"):
        field_header.kind_struct("WaveBank")


def test_an_appearance_field_names_its_kind():
    with pytest.raises(ValueError, match="names its kind"):
        surfel_field(3, role="appearance", doc="a colour", valid=(0, 1))
    with pytest.raises(ValueError, match="names its kind"):
        surfel_field(role="opacity", doc="an opacity", valid=(0, 1), kind="wave_bank")


@pytest.mark.parametrize("source", ["rasterize_cpu.cpp", "rasterize_cuda.cu", "rasterize.h", "ext.cpp"])
def test_the_tile_loops_and_the_bindings_name_no_kind(source):
    """The loops ask the composition (Appearance: has_gain, gain, colour, fold) and the falloff dispatch
    (with_falloff); no kind's field, struct or size check appears in them."""
    code = _code(CSRC / source)
    kind_fields = [f.name for f in SURFEL_FIELDS if f.kind]
    structs = [field_header.kind_struct(k) for k in BUILTIN_KINDS]
    for name in kind_fields + structs + ["TEX_CHANNELS", "G_WAVES", "G_BASE", "fold_gains", "wave_gain"]:
        assert not re.search(rf"\b{name}\b", code), f"{source} names {name}: ask the composition instead"
    assert not re.search(r"\bTS\s*(>|==|!=)\s*0\b", code), f"{source} tests the texture size: ask Appearance::has_gain"
    assert not re.search(r"\.s\s*>\s*S\(0\)", code), f"{source} branches on the falloff: use with_falloff"


def test_the_falloff_is_dispatched_in_one_place():
    code = _code(CSRC / "surfel_math.h")
    assert len(re.findall(r"\bs\s*>\s*S\(0\)\s*\)", code)) == 1, "with_falloff is the only branch on the falloff"
    assert "template <bool BETA" not in code
