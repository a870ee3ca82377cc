"""splatzoo: a model zoo for surface splatting (2DGS, 3D Gabor splatting and friends).

Importing splatzoo loads torch and nothing heavier: no compiled extension, no open3d.
"""
from .errors import SplatzooError
from .rasterizers import available_backends, rasterize
from .registry import ModelSpec
from .types import Camera, RenderOutput, Surfels
from .zoo import create_model, get_model_spec, list_models, load_model, save_model

__version__ = "0.1.0"

__all__ = ["Camera", "ModelSpec", "RenderOutput", "SplatzooError", "Surfels", "available_backends",
           "create_model", "get_model_spec", "list_models", "load_model", "rasterize", "save_model"]
