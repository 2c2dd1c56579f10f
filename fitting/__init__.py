"""fitting: recover material, light and fog parameters from images (builds on diffshade)."""

from ._cache import cache_info, enable_compilation_cache
from ._fit import fit
from ._models import ModelScore, compare_models, model_variants
from ._params import Param, ParamError, ParamSet, direction_frame, direction_of, tilt_of
from ._problem import FitError
from ._report import FitResult

__all__ = ["FitError", "FitResult", "ModelScore", "Param", "ParamError", "ParamSet", "cache_info",
           "compare_models", "direction_frame", "direction_of", "enable_compilation_cache", "fit", "model_variants",
           "tilt_of"]
