"""diffshade: a differentiable rasterize-and-shade pipeline for the classic local illumination model.

Pipeline (each stage a function of its own)::

    clip = camera.world_to_clip(mesh.vertices)
    ids = visibility(clip, mesh.faces, camera.resolution, layers)   # discrete, cached for fixed geometry
    frags = fragments(clip, mesh.faces, ids)                         # differentiable barycentrics/depth
    image = shade(scene, ids, options)                               # terms of docs/model.md, fog
"""

from ._camera import Camera, OpenCVCamera, rodrigues, undistort
from ._io import DEFAULT_SCENE, SceneError, default_scene, load_camera, load_scene, scene_from_dict
from ._mesh import Mesh, MeshError, box, combine, icosphere, load_mesh, mesh_from_arrays, quad
from ._raster import (
    Fragments,
    fragments,
    interpolate,
    pixel_centres,
    rasterize,
    visibility,
    visibility_passes,
)
from . import color
from ._antialias import antialias, face_adjacency, pixel_neighbours, silhouette_edges
from ._util import keep
from ._render import render, scene_visibility, shade, to_uint8, truncated_pixels
from ._trace import ray_counts
from ._scene import (
    AreaLights,
    DirectionalLights,
    Fog,
    Material,
    MultiLobeLights,
    PointLights,
    RenderOptions,
    Scene,
    SpotLights,
    no_area,
    no_directional,
    no_multi_lobe,
    no_point,
    no_spot,
)
from ._shade import blinn_to_phong, phong_to_blinn

__all__ = [
    "AreaLights", "no_area", "Camera", "OpenCVCamera", "rodrigues", "undistort", "DEFAULT_SCENE", "DirectionalLights", "Fog", "Fragments", "Material", "Mesh", "MeshError", "MultiLobeLights", "no_multi_lobe",
    "PointLights", "RenderOptions", "Scene", "SceneError", "SpotLights", "blinn_to_phong", "default_scene",
    "antialias", "face_adjacency", "fragments", "icosphere", "interpolate", "load_camera", "load_mesh", "load_scene", "mesh_from_arrays", "no_directional",
    "no_point", "no_spot", "phong_to_blinn", "pixel_centres", "rasterize", "render", "scene_from_dict",
    "scene_visibility", "shade", "to_uint8", "visibility", "visibility_passes", "box", "combine", "quad",
    "truncated_pixels",
    "ray_counts", "color", "keep", "pixel_neighbours", "silhouette_edges",
]
