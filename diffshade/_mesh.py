"""Triangle meshes: loading (through trimesh), validation and normals."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._util import as_float_array, safe_normalize


class MeshError(ValueError):
    """A mesh file or array that cannot be rendered; the message names the file and the problem."""


def _ids(x):
    return None if x is None else jnp.asarray(x, dtype=jnp.int32)


class Mesh(eqx.Module):
    """Vertices (traced, differentiable) and triangles (integer data, counter-clockwise = front).

    ``material_ids`` (optional, one per face) picks each face's material in
    :meth:`diffshade.Scene.all_materials`; without it every face uses material 0.
    """

    vertices: Float[Array, "V 3"] = eqx.field(converter=as_float_array)
    faces: Int[Array, "F 3"] = eqx.field(converter=lambda f: jnp.asarray(f, dtype=jnp.int32))
    material_ids: Int[Array, " F"] | None = eqx.field(converter=_ids, default=None)

    def face_normals(self, normalize: bool = True) -> Float[Array, "F 3"]:
        r"""Per-face normal :math:`(v_1 - v_0) \times (v_2 - v_0)` (unit length if ``normalize``).

        A zero-area face has the zero vector as its normal (finite gradients).
        """
        tri = self.vertices[self.faces]
        n = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return safe_normalize(n) if normalize else n

    def vertex_normals(self) -> Float[Array, "V 3"]:
        r"""Area-weighted vertex normals: :math:`\mathrm{normalize}(\sum_{f \ni v} (v_1 - v_0)\times(v_2 - v_0))`.

        docs/model.md §4. A vertex with no (non-degenerate) adjacent face gets the zero vector.
        """
        n = self.face_normals(normalize=False)
        acc = jnp.zeros_like(self.vertices)
        for k in range(3):
            acc = acc.at[self.faces[:, k]].add(n)
        return safe_normalize(acc)


def validate_arrays(vertices, faces, source: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Host-side checks of mesh arrays; raises :class:`MeshError` naming ``source`` and the problem."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{source}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"{source}: faces must have shape (F, 3) (triangles), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{source}: faces must be integer vertex indices, got dtype {f.dtype}")
    if len(f) == 0:
        raise MeshError(f"{source}: the mesh has no triangles: nothing to render")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise MeshError(
            f"{source}: {int(bad.sum())} vertex position(s) are NaN or infinite (first: vertex {int(np.argmax(bad))})"
        )
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"{source}: face indices must lie in [0, {len(v) - 1}], got [{f.min()}, {f.max()}]")
    return v, f.astype(np.int32)


_FACE_LINE = re.compile(r"^\s*f\s+(.*)$")


def _check_obj_faces(path: Path) -> None:
    # trimesh silently drops OBJ face lines with fewer than three indices; we report them.
    with open(path, "r", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            m = _FACE_LINE.match(line)
            if m and len(m.group(1).split()) < 3:
                raise MeshError(
                    f"{path}: line {lineno}: a face needs at least 3 vertex indices, got "
                    f"{len(m.group(1).split())} ({line.strip()!r})"
                )


def load_mesh(path: str | Path) -> Mesh:
    """Load a triangle mesh (OBJ, PLY, STL, GLB, OFF, ... through trimesh).

    Scenes are merged into one mesh; vertices that a format duplicates (STL facets, OBJ texture
    seams) are merged by position, since diffshade shades geometry only. Vertex colours,
    texture coordinates and materials in the file are not used. Raises :class:`MeshError` with
    the file name for a missing or unreadable file, a mesh with no triangles, malformed faces or
    non-finite vertex positions.
    """
    import trimesh

    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path}: mesh file not found")
    if not path.is_file():
        raise MeshError(f"{path}: not a file")
    if path.suffix.lower() == ".obj":
        _check_obj_faces(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tm = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"{path}: could not read the mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(tm, trimesh.Trimesh) or len(getattr(tm, "faces", [])) == 0:
        raise MeshError(f"{path}: the file has no triangles: nothing to render")
    v = np.asarray(tm.vertices, dtype=np.float64)
    f = np.asarray(tm.faces)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise MeshError(
            f"{path}: {int(bad.sum())} vertex position(s) are NaN or infinite (first: vertex {int(np.argmax(bad))})"
        )
    # Merge vertices that coincide (to trimesh's tolerance), ignoring UV/normal/colour splits:
    # diffshade shades geometry only.
    geom = trimesh.Trimesh(vertices=v, faces=f, process=False)
    geom.merge_vertices(merge_tex=True, merge_norm=True)
    v, f = validate_arrays(geom.vertices, geom.faces, str(path))
    return Mesh(vertices=v, faces=f)


def icosphere(subdivisions: int = 3, radius: float = 1.0) -> Mesh:
    """A unit icosphere (``trimesh.creation.icosphere``): 20·4^subdivisions faces."""
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(vertices=np.asarray(tm.vertices), faces=np.asarray(tm.faces))


def mesh_from_arrays(vertices, faces, name: str = "mesh") -> Mesh:
    """A :class:`Mesh` from arrays, validated on the host."""
    if isinstance(vertices, jax.core.Tracer):
        return Mesh(vertices=vertices, faces=faces)
    v, f = validate_arrays(vertices, faces, name)
    return Mesh(vertices=v, faces=f)


def combine(*meshes: Mesh) -> Mesh:
    """One mesh from several, the faces of the ``i``-th carrying material id ``i``.

    Use with ``Scene(material=<id 0>, materials=(<id 1>, ...))``.
    """
    verts, faces, ids, offset = [], [], [], 0
    for i, m in enumerate(meshes):
        if m.material_ids is not None:
            raise ValueError(f"combine: mesh {i} already has material ids; combine meshes without them")
        verts.append(m.vertices)
        faces.append(m.faces + offset)
        ids.append(jnp.full(m.faces.shape[0], i, jnp.int32))
        offset += m.vertices.shape[0]
    return Mesh(vertices=jnp.concatenate(verts), faces=jnp.concatenate(faces), material_ids=jnp.concatenate(ids))


def box(extents=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0)) -> Mesh:
    """A closed axis-aligned box (12 outward-facing triangles), ``trimesh.creation.box``."""
    import trimesh

    tm = trimesh.creation.box(extents=np.asarray(extents, float))
    return Mesh(vertices=np.asarray(tm.vertices) + np.asarray(center, float), faces=np.asarray(tm.faces))


def quad(size=(1.0, 1.0), center=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), divisions: int = 1) -> Mesh:
    """A flat rectangle of ``size`` centred at ``center``, facing ``normal`` (its front side),
    split into ``divisions``² squares of two triangles each."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    helper = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    k = int(divisions)
    s = np.linspace(-0.5, 0.5, k + 1)
    gu, gv = np.meshgrid(s * size[0], s * size[1], indexing="xy")
    verts = np.asarray(center, float) + gu.reshape(-1, 1) * u + gv.reshape(-1, 1) * v
    faces = []
    for j in range(k):
        for i in range(k):
            a, b, c, d = j * (k + 1) + i, j * (k + 1) + i + 1, (j + 1) * (k + 1) + i + 1, (j + 1) * (k + 1) + i
            faces += [(a, b, c), (a, c, d)]
    return Mesh(vertices=verts, faces=np.asarray(faces))
