"""splatzoo's members as nerfstudio methods: `ns-train splatzoo-gabor` (and splatzoo-2dgs, -beta, -beta-gabor,
-textured, -neural-gabor, -gabor-adaptive) train through splatzoo's own step (its densification, strategies, losses
and Adam), on any folder splatzoo reads (the `splatzoo-data` dataparser) or on nerfstudio's own dataparsers;
`ns-viewer`, `ns-eval` and `ns-render` work on their outputs, and so does splatzoo (`read_nerfstudio_output`).

Only the reader lives at this level: it needs no nerfstudio, so splatzoo's own commands read ns-train's outputs in
any environment. The modules that define the methods (methods, model, data, trainer) import nerfstudio; they are
loaded by nerfstudio through the `nerfstudio.method_configs` and `nerfstudio.dataparser_configs` entry points, in the
environment `scripts/install.sh --nerfstudio` makes (docs/nerfstudio.md).
"""
from .output import is_nerfstudio_output, open_nerfstudio_output, read_nerfstudio_output

__all__ = ["is_nerfstudio_output", "open_nerfstudio_output", "read_nerfstudio_output"]
