"""fitting: recover material, light and fog parameters from images (builds on diffshade).

``fit(scene, opts, Observations(targets, ...), free, strategy=VarPro(...))`` returns a
:class:`FitResult`; :func:`compare_models` asks which terms the images support. Everything else
lives in private modules named by what they compute (``_params``, ``_problem``, ``_linear``,
``_varpro``, ``_starts``, ``_restarts``, ``_polish``, ``_basins``, ``_intervals``, ``_albedo``,
``_block_solver``, ``_report``, ``_models``, ``_cache``, ``_noise``); :func:`downsample`
area-averages a target and keeps what was clipped; design notes: docs/fit-design-notes.md."""

from ._cache import cache_info, enable_compilation_cache
from ._downsample import Downsampled, downsample
from ._fit import fit
from ._gains import GainGauge, mean_gauge
from ._holdout import Holdout, holdout_fit
from ._models import (
    DIFFUSE_MODELS,
    IMAGING_TERMS,
    SPECULAR_MODELS,
    ModelScore,
    compare_models,
    imaging_variants,
    model_variants,
    not_told_apart,
)
from ._observations import CAPTURE_CLIP_MARGIN, CAPTURE_MARGIN, FitError, Observations, Optimistix, Strategy, VarPro
from ._params import Param, ParamError, ParamSet, direction_frame, direction_of, tilt_of
from ._photometric import Capture, frame_check, load_photometric_stereo, sphere_from_mask
from ._report import Diagnostics, FitResult, Intervals, ResidualStats

__all__ = [
    "CAPTURE_CLIP_MARGIN",
    "CAPTURE_MARGIN",
    "Holdout",
    "IMAGING_TERMS",
    "holdout_fit",
    "Capture",
    "Diagnostics",
    "Downsampled",
    "FitError",
    "FitResult",
    "GainGauge",
    "Intervals",
    "ModelScore",
    "Observations",
    "Optimistix",
    "ResidualStats",
    "Strategy",
    "VarPro",
    "Param",
    "ParamError",
    "ParamSet",
    "cache_info",
    "compare_models",
    "direction_frame",
    "direction_of",
    "downsample",
    "enable_compilation_cache",
    "fit",
    "frame_check",
    "imaging_variants",
    "load_photometric_stereo",
    "mean_gauge",
    "sphere_from_mask",
    "model_variants",
    "not_told_apart",
    "DIFFUSE_MODELS",
    "SPECULAR_MODELS",
    "tilt_of",
]
