"""splatzoo's stand-in for torchvision in a CPU nerfstudio environment: the two functions nerfstudio calls
(`utils.save_image`, `transforms.functional.resize`), in plain torch and PIL. Anything else is absent on purpose."""
from . import transforms, utils

__version__ = "0.28.0+splatzoo.stub"
__all__ = ["transforms", "utils"]
