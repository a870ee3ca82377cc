"""splatzoo: a model zoo for surface splatting (2DGS, 3D Gabor splatting and friends).

Importing splatzoo loads torch and nothing heavier: no compiled extension, no open3d.
"""
import os as _os

# OpenMP threads that spin while waiting make every small torch op and every tile loop crawl as soon as another
# process competes for the cores (measured: a [5000,3]@[3,3] matmul 0.05 ms -> 15 ms, a 128x128 render 10 ->
# 200 ms). Sleeping waiters cost microseconds. Only effective if set before torch starts its OpenMP runtime.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .errors import SplatzooError  # noqa: E402
from .model_files import load_model, open_model, write_model  # noqa: E402
from .model_ply import load_ply  # noqa: E402
from .rasterizers import available_backends, rasterize
from .registry import ModelSpec
from .types import Camera, RenderOutput, Surfels
from .zoo import create_model, get_model_spec, list_models, save_model

__version__ = "0.1.0"

__all__ = ["Camera", "ModelSpec", "RenderOutput", "SplatzooError", "Surfels", "available_backends",
           "create_model", "get_model_spec", "list_models", "load_model", "load_ply", "open_model", "rasterize",
           "save_model", "write_model"]
