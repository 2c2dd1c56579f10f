"""diffshade: a differentiable rasterize-and-shade pipeline for the classic illumination model.

The render is a chain of stages, each a public function (what :func:`shade` calls)::

    clip = scene.camera.world_to_clip(scene.mesh.vertices)
    ids = visibility(clip, scene.mesh.faces, scene.camera.resolution, opts.layers)  # discrete
    frags = fragments(clip, scene.mesh.faces, ids)              # differentiable barycentrics, depth
    surface = surface_points(scene, frags, opts.raster)         # flat / Gouraud / Phong sites
    vis = light_visibility(scene, surface, opts.shadows)        # None, shadow maps or rays
    color = illuminate(scene, surface, opts.lighting, vis, opts.output)
    color = secondary_rays(scene, surface, color, opts)         # mirrors and glass (depth 0: none)
    image = composite(scene, surface, color, opts.fog, opts.transparency, opts.output)
"""

from . import color, images
from ._antialias import antialias, face_adjacency, pixel_neighbours, silhouette_edges
from ._camera import Camera, OpenCVCamera, OrthographicCamera, rodrigues, undistort
from ._composite import composite
from ._domains import Domain, check_scene
from ._fast import kernel_partials
from ._io import DEFAULT_SCENE, SceneError, default_scene, load_camera, load_scene, scene_from_dict
from ._lighting import LightVisibility, illuminate
from ._mesh import Mesh, MeshError, box, combine, icosphere, load_mesh, mesh_from_arrays, quad
from ._mtl import load_material, save_material
from ._normal_map import integrate_normals, normal_map_mesh, read_normal_map
from ._options import FogModel, Lighting, Output, Raster, Rays, RenderOptions, ShadowMaps, ShadowRays, Transparency
from ._raster import Fragments, fragments, interpolate, pixel_centres, rasterize, visibility, visibility_passes
from ._render import light_visibility, ray_counts, render, scene_visibility, shade, to_uint8, truncated_pixels
from ._scene import (
    AreaLights,
    DirectionalLights,
    Fog,
    Material,
    MultiLobeLights,
    PointLights,
    Scene,
    SpotLights,
    no_area,
    no_directional,
    no_multi_lobe,
    no_point,
    no_spot,
)
from ._shade import blinn_to_phong, phong_to_blinn
from ._surface import Needs, Sites, Surface, needs, surface_points, texture_coordinates
from ._texture import Texture, level_of_detail, mip_pyramid, sample, sample_weights, texture_from_image
from ._trace import secondary_rays
from ._util import keep
from .images import Image, ImageError, read_image, write_image

__all__ = [
    "kernel_partials",
    "AreaLights",
    "no_area",
    "Camera",
    "OpenCVCamera",
    "OrthographicCamera",
    "integrate_normals",
    "normal_map_mesh",
    "read_normal_map",
    "rodrigues",
    "undistort",
    "DEFAULT_SCENE",
    "DirectionalLights",
    "Fog",
    "Fragments",
    "Material",
    "Texture",
    "texture_from_image",
    "mip_pyramid",
    "sample",
    "sample_weights",
    "level_of_detail",
    "texture_coordinates",
    "Mesh",
    "MeshError",
    "MultiLobeLights",
    "no_multi_lobe",
    "PointLights",
    "RenderOptions",
    "Scene",
    "SceneError",
    "Domain",
    "check_scene",
    "SpotLights",
    "blinn_to_phong",
    "default_scene",
    "antialias",
    "face_adjacency",
    "fragments",
    "icosphere",
    "interpolate",
    "load_camera",
    "load_mesh",
    "load_material",
    "save_material",
    "load_scene",
    "mesh_from_arrays",
    "no_directional",
    "no_point",
    "no_spot",
    "phong_to_blinn",
    "pixel_centres",
    "rasterize",
    "render",
    "scene_from_dict",
    "scene_visibility",
    "shade",
    "to_uint8",
    "visibility",
    "visibility_passes",
    "box",
    "combine",
    "quad",
    "truncated_pixels",
    "ray_counts",
    "color",
    "images",
    "Image",
    "ImageError",
    "read_image",
    "write_image",
    "keep",
    "pixel_neighbours",
    "silhouette_edges",
    "Raster",
    "Lighting",
    "ShadowMaps",
    "ShadowRays",
    "Rays",
    "FogModel",
    "Transparency",
    "Output",
    "Surface",
    "Sites",
    "Needs",
    "needs",
    "surface_points",
    "light_visibility",
    "LightVisibility",
    "illuminate",
    "secondary_rays",
    "composite",
]
