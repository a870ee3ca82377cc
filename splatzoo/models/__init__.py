"""Built-in models, registered here by explicit import; plugins arrive through the registry's entry points."""
from __future__ import annotations

from ..registry import ModelSpec, register_model
from .beta import BetaConfig, BetaModel
from .beta_gabor import BetaGaborConfig, BetaGaborModel
from .gabor import AdaptiveGaborConfig, BaselineAConfig, BaselineBModel, BaselineCModel, GaborConfig, GaborModel
from .neural_gabor import NeuralGaborConfig, NeuralGaborModel
from .surfel2d import Surfel2DConfig, Surfel2DModel
from .textured import TexturedConfig, TexturedModel

register_model(ModelSpec("2dgs", Surfel2DModel, Surfel2DConfig,
                         "2D Gaussian surfels, one colour each (optional spherical harmonics)"))
register_model(ModelSpec("beta", BetaModel, BetaConfig,
                         "2D surfels with a learned Beta-kernel falloff (1 - s rho/2)^(1/s): bounded, sharper support"))
register_model(ModelSpec("textured", TexturedModel, TexturedConfig,
                         "2DGS surfels with a small RGBA texture each (texture_size x texture_size texels): colour "
                         "residual and transparency inside a surfel (Textured Gaussians)"))
register_model(ModelSpec("gabor", GaborModel, GaborConfig,
                         "3D Gabor surfels: N wave orientations with learnable frequency, weight and phase"))
register_model(ModelSpec("gabor-adaptive", GaborModel, AdaptiveGaborConfig,
                         "gabor with waves only where they pay: 8 orientations to start, late in training the waves "
                         "whose removal costs the training views under 0.02 dB go"))
register_model(ModelSpec("beta-gabor", BetaGaborModel, BetaGaborConfig,
                         "gabor-adaptive's waves (kept only where they pay), each with a colour and direction of its "
                         "own, on surfels with beta's learned falloff; under a byte budget it sheds waves or its "
                         "weakest surfels by measured cost"))
register_model(ModelSpec("neural-gabor", NeuralGaborModel, NeuralGaborConfig,
                         "surfels whose colour is a tiny per-surfel sine network of (u, v) and the view direction, "
                         "with frequency-aware densification (Neural Gabor splatting)"))
register_model(ModelSpec("baseline-a", GaborModel, BaselineAConfig,
                         "ablation A: Gabor surfels with a single wave"))
register_model(ModelSpec("baseline-b", BaselineBModel, GaborConfig,
                         "ablation B: N waves all along the local u axis"))
register_model(ModelSpec("baseline-c", BaselineCModel, GaborConfig,
                         "ablation C: Gabor surfels with phases fixed at zero"))
