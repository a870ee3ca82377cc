"""Write the preset dictionary of the packed-file headers of the current format version (splatzoo/packing.py).

The dictionary holds the headers of the built-in models at their default options, each of 10 primitives with values
that vary as trained ones do, with the render settings a training run records, at the reduced precisions, as created
and with what a byte budget sheds shed (no waves). A header without render settings finds its parts in them. The
headers a small budget writes most (8-bit beta-gabor and 2dgs) come last, where deflate's distances are shortest. A
dictionary is fixed for good once files are written with it (they name it by checksum), so this refuses to replace
one that exists: a new dictionary comes with a new format version.

    python scripts/make_header_dictionary.py
"""
from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import torch

from splatzoo import packing
from splatzoo.zoo import create_model, list_models

REDUCED = ("float16", "8bit")  # a float32 file's header is a small part of it
LAST = ("2dgs", "beta-gabor")  # the members a small budget is spent on, nearest the end
TRAINED = {"antialias": True, "background": [0.0, 0.0, 0.0]}  # what `splatzoo train` records on synthetic scenes


def _varied(name: str):
    """Model `name` of 10 primitives whose float values vary, as a trained model's do (a constant column can
    need float32 ranges)."""
    g = torch.Generator().manual_seed(0)
    model = create_model(name, torch.rand(10, 3, generator=g), torch.rand(10, 3, generator=g))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return model


def headers() -> list[str]:
    lines = []
    for name in sorted(list_models(), key=lambda n: (n in LAST, LAST.index(n) if n in LAST else 0, n)):
        model = _varied(name)
        shed = copy.deepcopy(model).shed_richness()
        for precision in REDUCED:
            variants = []
            for m in (shed, model):
                ckpt = m.checkpoint()
                variants.append(packing.packed_parts({**ckpt, **TRAINED}, precision)[0])
            texts = dict.fromkeys(json.dumps(h, separators=(",", ":")) for h in variants)
            lines += list(texts)
    return lines


def main() -> int:
    target = Path(packing.__file__).with_name(packing.DICTIONARY_FILES[packing.VERSION])
    if target.exists():
        print(f"{target} exists and version-{packing.VERSION} files need it as it is; a new dictionary needs a new "
              "format version", file=sys.stderr)
        return 1
    text = "\n".join(headers()) + "\n"
    if len(text) > 32768:
        print(f"the dictionary would take {len(text)} bytes; deflate looks back 32768 at most", file=sys.stderr)
        return 1
    target.write_text(text)
    print(f"wrote {target} ({len(text)} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
