"""diffshade: a differentiable rasterize-and-shade pipeline for the classic local illumination model."""

from ._camera import Camera
from ._raster import Fragments, fragments, interpolate, pixel_centres, rasterize, visibility, visibility_passes

__all__ = [
    "Camera",
    "Fragments",
    "fragments",
    "interpolate",
    "pixel_centres",
    "rasterize",
    "visibility",
    "visibility_passes",
]
