"""Triangle meshes: loading (through trimesh), validation and normals."""

from __future__ import annotations

import dataclasses
import io
import re
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._util import as_float_array, safe_normalize, take


class MeshError(ValueError):
    """A mesh file or array that cannot be rendered; the message names the file and the problem."""


def _ids(x):
    return None if x is None else jnp.asarray(x, dtype=jnp.int32)


class Mesh(eqx.Module):
    """Vertices (traced, differentiable) and triangles (integer data, counter-clockwise = front).

    ``material_ids`` (optional, one per face) picks each face's material in
    :meth:`diffshade.Scene.all_materials`; without it every face uses material 0. ``normals``
    (optional, one per vertex) are the normals a mesh file gives (OBJ ``vn``, PLY ``nx ny nz``):
    :meth:`vertex_normals` returns them, normalised, instead of computing them; they are data
    (they do not follow the vertices in a fit that moves them). ``colors`` (optional, one linear
    RGB per vertex) are per-vertex reflectances, used where ``RenderOptions.vertex_color`` asks.
    ``uv`` (optional, one ``(u, v)`` per vertex, :math:`v = 0` at the bottom of a map) are the
    texture coordinates a material's maps are sampled at (OBJ ``vt``; docs/model.md §15).
    ``unit_normals`` (static) says the ``normals`` are unit vectors already, used as they are
    (:meth:`with_vertex_normals` sets it). ``adjacency`` (optional, one row per face) is the face across each edge
    (:func:`diffshade.face_adjacency`), which ``RenderOptions.antialias`` needs: computed from the
    faces where they are concrete, or beforehand with :meth:`with_adjacency` for a mesh passed
    into ``jax.jit``.
    """

    vertices: Float[Array, "V 3"] = eqx.field(converter=as_float_array)
    faces: Int[Array, "F 3"] = eqx.field(converter=lambda f: jnp.asarray(f, dtype=jnp.int32))
    material_ids: Int[Array, " F"] | None = eqx.field(converter=_ids, default=None)
    normals: Float[Array, "V 3"] | None = eqx.field(
        converter=lambda x: None if x is None else as_float_array(x), default=None
    )
    colors: Float[Array, "V 3"] | None = eqx.field(
        converter=lambda x: None if x is None else as_float_array(x), default=None
    )
    adjacency: Int[Array, "F 3"] | None = eqx.field(converter=_ids, default=None)
    uv: Float[Array, "V 2"] | None = eqx.field(
        converter=lambda x: None if x is None else as_float_array(x), default=None
    )
    # the normals are unit vectors already, used as they are (with_vertex_normals'): normalised
    # again they would differ from the renderer's own in the last bit
    unit_normals: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        nv = self.vertices.shape[0]
        if self.adjacency is not None and self.adjacency.shape != self.faces.shape:
            raise ValueError(
                f"Mesh.adjacency must be shaped {self.faces.shape}, one face per edge, got {self.adjacency.shape}"
            )
        for name in ("normals", "colors"):
            x = getattr(self, name)
            if x is not None and x.shape != (nv, 3):
                raise ValueError(f"Mesh.{name} must be shaped ({nv}, 3), one per vertex, got {x.shape}")
        if self.uv is not None and self.uv.shape != (nv, 2):
            raise ValueError(f"Mesh.uv must be shaped ({nv}, 2), one (u, v) per vertex, got {self.uv.shape}")

    def with_adjacency(self) -> "Mesh":
        """This mesh with its :attr:`adjacency` computed (on the host, from the faces)."""
        from ._antialias import face_adjacency

        return eqx.tree_at(
            lambda m: m.adjacency,
            self,
            jnp.asarray(face_adjacency(np.asarray(self.faces))),
            is_leaf=lambda x: x is None,
        )

    def face_normals(self, normalize: bool = True) -> Float[Array, "F 3"]:
        r"""Per-face normal :math:`(v_1 - v_0) \times (v_2 - v_0)` (unit length if ``normalize``).

        A zero-area face has the zero vector as its normal (finite gradients).
        """
        tri = take(self.vertices, self.faces)
        n = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return safe_normalize(n) if normalize else n

    def vertex_normals(self) -> Float[Array, "V 3"]:
        r"""Area-weighted vertex normals: :math:`\mathrm{normalize}(\sum_{f \ni v} (v_1 - v_0)\times(v_2 - v_0))`.

        docs/model.md §4. A vertex whose adjacent faces' cross products cancel (opposite
        duplicate faces, a fold; :data:`CANCEL` below) gets the zero vector, as does one with no
        non-degenerate adjacent face: the sum there is float rounding, whose direction would
        change with the precision and the order of the sum. A mesh with file ``normals``
        returns those, normalised. In float32 on the CPU the native kernel computes them
        (``csrc/normals.cc``: the same bits in every program, jitted or not, and no scatter in
        the program; derivatives by the JAX implementation's), elsewhere the JAX stages.
        """
        if self.normals is not None:
            return self.normals if self.unit_normals else safe_normalize(self.normals)
        if _native_normals_apply(self.vertices):
            return _normals_native(self.vertices, self.faces)
        return _normals_jax(self.vertices, self.faces)

    def with_vertex_normals(self) -> "Mesh":
        """This mesh with :attr:`normals` set to :meth:`vertex_normals` computed once (where it
        gives none), for a program that never moves the vertices, which then holds no scatter
        over the faces (a loop on XLA's CPU backend) to compute them: by the native kernel in
        float32 (the bits every render computes), else on the host in float64, the cancelling
        sums decided as in the scene's dtype."""
        if self.normals is not None:
            return self
        if _native_normals_apply(self.vertices):
            out = _normals_native(self.vertices, self.faces)
        else:
            out = jnp.asarray(_normals_host(self.vertices, self.faces), self.vertices.dtype)
        mesh = eqx.tree_at(lambda m: m.normals, self, out, is_leaf=lambda x: x is None)
        return dataclasses.replace(mesh, unit_normals=True)


def _normals_jax(vertices, faces):
    """:meth:`Mesh.vertex_normals` in JAX (any dtype and device; the native kernel's derivatives)."""
    tri = take(vertices, faces)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = jnp.cross(e1, e2)
    # each face's cross product is exact to a few ulps of |e1||e2| (its rounding bound; a
    # decision, not differentiated: no gradient through the square root at a zero edge)
    scale = jax.lax.stop_gradient(jnp.sqrt(jnp.sum(e1 * e1, -1) * jnp.sum(e2 * e2, -1)))
    nb = jnp.concatenate([n, scale[:, None]], axis=1)
    acc = jnp.zeros((vertices.shape[0], 4), nb.dtype)
    for k in range(3):
        acc = acc.at[faces[:, k]].add(nb)
    s, bound = acc[:, :3], acc[:, 3:]
    tol = CANCEL * jnp.finfo(s.dtype).eps * bound
    return jnp.where(jnp.sum(s * s, -1, keepdims=True) > tol * tol, safe_normalize(s), 0.0)


def _normals_host(vertices, faces) -> np.ndarray:
    """:meth:`Mesh.vertex_normals` on the host in float64, the cancelling sums decided by the
    ε of ``vertices``' dtype."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces)
    tri = v[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    nb = np.concatenate([n, (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))[:, None]], axis=1)
    acc = np.zeros((len(v), 4))
    for k in range(3):
        np.add.at(acc, f[:, k], nb)
    s, bound = acc[:, :3], acc[:, 3:]
    length = np.linalg.norm(s, axis=1, keepdims=True)
    ok = length > CANCEL * np.finfo(np.dtype(vertices.dtype)).eps * bound
    return np.where(ok, s / np.where(ok, length, 1.0), 0.0)


def _native_normals_apply(vertices) -> bool:
    """Whether the native kernel computes the normals of ``vertices`` (float32, on the CPU)."""
    if jnp.result_type(vertices) != jnp.float32 or jax.default_backend() != "cpu" or vertices.ndim != 2:
        return False
    from . import _native

    return _native.available()


@jax.custom_jvp
def _normals_native(vertices, faces):
    from . import _native

    call = jax.ffi.ffi_call(
        _native.ensure_registered("diffshade_normals"),
        jax.ShapeDtypeStruct(vertices.shape, jnp.float32),
        vmap_method="broadcast_all",
    )
    return call(vertices, jnp.asarray(faces, jnp.int32), cancel=np.float32(CANCEL))


@_normals_native.defjvp
def _normals_native_jvp(primals, tangents):
    vertices, faces = primals
    dv = tangents[0]
    _, dn = jax.jvp(lambda v: _normals_jax(v, faces), (vertices,), (dv,))
    return _normals_native(vertices, faces), dn


CANCEL = 16.0
r"""A vertex normal's sum :math:`\sum_f n_f` counts as cancelled (the zero vector) where its
length is at most ``CANCEL`` × the dtype's ε × :math:`\sum_f |e_1||e_2|`, the bound of its
faces' rounding: a scanned mesh's opposite duplicate faces sum to exactly zero in exact
arithmetic and to rounding in floats (the Stanford bunny: 22 of 8,171 vertices, the next
smallest sum 0.38 of its bound)."""


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
    if len(v) == 0:
        raise MeshError(f"{source}: the mesh has faces but no vertices")
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
    with open(path, errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            m = _FACE_LINE.match(line)
            if m and len(m.group(1).split()) < 3:
                raise MeshError(
                    f"{path}: line {lineno}: a face needs at least 3 vertex indices, got "
                    f"{len(m.group(1).split())} ({line.strip()!r})"
                )


def _obj_as_fans(path: Path) -> bytes | None:
    """The OBJ's text with every polygon face line (more than 3 corners) written as the triangles
    of its fan from the first corner, in the file's order, ``(a,b,c),(a,c,d),...``: what OpenGL
    draws of a ``GL_POLYGON`` and the usual loaders make of it (trimesh splits a quad
    ``(a,b,c),(c,d,a)`` and puts the second halves after all the first ones: in flat shading from
    the provoking vertex the second triangle took ``a``'s colour, not ``d``'s). None if the file
    has no polygons."""
    data = path.read_bytes()
    lines, changed = data.split(b"\n"), False
    for i, line in enumerate(lines):
        m = re.match(rb"^(\s*)f\s+(.*)$", line)
        if not m:
            continue
        corners = m.group(2).split(b"#", 1)[0].split()
        if len(corners) > 3:
            changed = True
            a = corners[0]
            lines[i] = b"\n".join(
                m.group(1) + b"f " + b" ".join((a, corners[k], corners[k + 1])) for k in range(1, len(corners) - 1)
            )
    return b"\n".join(lines) if changed else None


VERTEX_MODES = ("authored", "merged")


COLOR_MODES = ("srgb", "linear", "ignore")


def _file_colors(parts, path, encoding: str):
    """The file's per-vertex colours as linear RGB in [0, 1] (None if it has none)."""
    if encoding == "ignore":
        return None
    cols = []
    for g in parts:
        vis = getattr(g, "visual", None)
        if vis is None or getattr(vis, "kind", None) != "vertex":
            return None
        c = np.asarray(vis.vertex_colors)
        if c.shape[0] != len(g.vertices):
            return None
        cols.append(c[:, :3])
    c = np.concatenate(cols).astype(np.float64)
    c = c / 255.0 if np.issubdtype(cols[0].dtype, np.integer) else c
    if not np.isfinite(c).all() or (c < 0).any() or (c > 1).any():
        raise MeshError(f"{path}: vertex colours must be finite and in [0, 1]")
    from .color import decode

    return np.asarray(decode(c, encoding), np.float64)


def _trimesh_parts(path: Path) -> list:
    """The file's geometries through trimesh, placed by its scene graph (a single mesh is its own
    part); an OBJ's polygons as fans (:func:`_obj_as_fans`)."""
    import trimesh

    fans = None
    if path.suffix.lower() == ".obj":
        _check_obj_faces(path)
        fans = _obj_as_fans(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if fans is None:
                loaded = trimesh.load(str(path), process=False)
            else:  # (its material library found beside the file)
                loaded = trimesh.load(
                    io.BytesIO(fans),
                    file_type="obj",
                    resolver=trimesh.resolvers.FilePathResolver(str(path)),
                    process=False,
                )
            # a scene's geometries, placed by its graph (a single mesh is its own part)
            parts = (
                [loaded]
                if isinstance(loaded, trimesh.Trimesh)
                else (
                    [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
                    if isinstance(loaded, trimesh.Scene)
                    else []
                )
            )
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"{path}: could not read the mesh ({type(exc).__name__}: {exc})") from exc
    return parts


def load_mesh(path: str | Path, vertices: str = "authored", colors: str = "srgb") -> Mesh:
    """Load a triangle mesh (OBJ, PLY, STL, GLB, OFF, ... through trimesh).

    ``vertices = "authored"`` (the default) keeps the file's vertices as written, and its vertex
    normals (OBJ ``vn``, PLY ``nx ny nz``) when it has them for every vertex: a mesh whose author
    split vertices for hard edges, or wrote their own normals, is shaded as authored (as an
    OpenGL program drawing the file would). Without file normals they are computed (area-weighted)
    over the file's vertices, so split vertices keep hard edges (an STL's facets look flat).
    ``vertices = "merged"`` merges vertices that coincide in position (ignoring normal, texture and
    colour splits) and computes smooth normals: what a file of triangle soup needs to look smooth.

    Scenes are merged into one mesh. Per-vertex colours (PLY ``red green blue``, OBJ ``v x y z r g
    b``) become ``Mesh.colors``, decoded as ``colors`` says: ``"srgb"`` (the default: 8-bit colours
    in files are display values), ``"linear"``, or ``"ignore"``; merged vertices average theirs.
    An OBJ polygon (a face of more than 3 corners) becomes the fan of triangles from its first
    corner, in the order of the file (what OpenGL draws of it, and the usual loaders). Texture coordinates (OBJ ``vt``) become ``Mesh.uv`` (authored vertices only: merging ignores
    them); the file's materials are read by :func:`diffshade.load_material`. Raises :class:`MeshError` with the file name for a missing or unreadable file, a
    mesh with no triangles, malformed faces, non-finite vertex positions or normals.
    """
    if vertices not in VERTEX_MODES:
        raise MeshError(f"{path}: vertices must be one of {VERTEX_MODES}, got {vertices!r}")
    if colors not in COLOR_MODES:
        raise MeshError(f"{path}: colors must be one of {COLOR_MODES}, got {colors!r}")
    import trimesh

    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path}: mesh file not found")
    if not path.is_file():
        raise MeshError(f"{path}: not a file")
    parts = _trimesh_parts(path)
    parts = [g for g in parts if len(getattr(g, "faces", [])) > 0]
    if not parts:
        raise MeshError(f"{path}: the file has no triangles: nothing to render")
    offsets = np.cumsum([0] + [len(g.vertices) for g in parts])
    v = np.concatenate([np.asarray(g.vertices, dtype=np.float64) for g in parts])
    f = np.concatenate([np.asarray(g.faces) + o for g, o in zip(parts, offsets[:-1])])
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise MeshError(
            f"{path}: {int(bad.sum())} vertex position(s) are NaN or infinite (first: vertex {int(np.argmax(bad))})"
        )
    col = _file_colors(parts, path, colors)
    if vertices == "merged":
        # Merge vertices that coincide (to trimesh's tolerance), ignoring UV/normal/colour splits.
        geom = trimesh.Trimesh(vertices=v, faces=f, process=False)
        geom.merge_vertices(merge_tex=True, merge_norm=True)
        v2, f2 = validate_arrays(geom.vertices, geom.faces, str(path))
        merged = None
        if col is not None:  # each merged vertex: the mean colour of the file's vertices it replaces
            old_to_new = np.zeros(len(v), np.int64)
            old_to_new[np.asarray(f).reshape(-1)] = np.asarray(f2).reshape(-1)
            used = np.zeros(len(v), bool)
            used[np.asarray(f).reshape(-1)] = True
            merged = np.zeros((len(v2), 3))
            np.add.at(merged, old_to_new[used], col[used])
            merged /= np.maximum(np.bincount(old_to_new[used], minlength=len(v2)), 1)[:, None]
        return Mesh(vertices=v2, faces=f2, colors=merged)
    v, f = validate_arrays(v, f, str(path))
    # trimesh keeps normals read from the file in its cache (and computes them only on request)
    file_normals = [g._cache.cache.get("vertex_normals") for g in parts]
    normals = None
    if all(n is not None and np.shape(n) == (len(g.vertices), 3) for n, g in zip(file_normals, parts)):
        normals = np.concatenate([np.asarray(n, np.float64) for n in file_normals])
        bad = ~np.isfinite(normals).all(axis=1)
        if bad.any():
            raise MeshError(
                f"{path}: {int(bad.sum())} vertex normal(s) are NaN or infinite (first: vertex {int(np.argmax(bad))})"
            )
        zero = np.linalg.norm(normals, axis=1) == 0
        if zero.any():  # a zero normal shades nothing: computed ones stand in for those
            normals[zero] = np.asarray(Mesh(vertices=v, faces=f).vertex_normals())[zero]
    return Mesh(vertices=v, faces=f, normals=normals, colors=col, uv=_file_uv(parts, path))


def _file_uv(parts, path):
    """The file's texture coordinates, one per (authored, so split) vertex; None without them."""
    uvs = []
    for g in parts:
        uv = getattr(getattr(g, "visual", None), "uv", None)
        if uv is None or np.shape(uv) != (len(g.vertices), 2):
            return None
        uvs.append(np.asarray(uv, np.float64))
    uv = np.concatenate(uvs)
    bad = ~np.isfinite(uv).all(axis=1)
    if bad.any():
        raise MeshError(
            f"{path}: {int(bad.sum())} texture coordinate(s) are NaN or infinite (first: vertex {int(np.argmax(bad))})"
        )
    return uv


def icosphere(subdivisions: int = 3, radius: float = 1.0) -> Mesh:
    """A unit icosphere (``trimesh.creation.icosphere``): 20·4^subdivisions faces."""
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(vertices=np.asarray(tm.vertices), faces=np.asarray(tm.faces))


def mesh_from_arrays(vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"], name: str = "mesh") -> Mesh:
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
    # file normals kept where a mesh has them (the others' are computed once, here)
    normals = None if all(m.normals is None for m in meshes) else jnp.concatenate([m.vertex_normals() for m in meshes])
    if any(m.colors is not None for m in meshes) and not all(m.colors is not None for m in meshes):
        raise ValueError("combine: some meshes have vertex colours and some do not; give every mesh colours or none")
    colors = None if meshes[0].colors is None else jnp.concatenate([m.colors for m in meshes])
    # texture coordinates kept where a mesh has them; (0, 0) for the vertices of one without
    # (its material must have no maps: the renderer samples them there)
    uv = None
    if any(m.uv is not None for m in meshes):
        uv = jnp.concatenate([m.uv if m.uv is not None else jnp.zeros((m.vertices.shape[0], 2)) for m in meshes])
    return Mesh(
        vertices=jnp.concatenate(verts),
        faces=jnp.concatenate(faces),
        material_ids=jnp.concatenate(ids),
        normals=normals,
        colors=colors,
        uv=uv,
    )


def box(
    extents: tuple[float, float, float] = (1.0, 1.0, 1.0), center: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> Mesh:
    """A closed axis-aligned box (12 outward-facing triangles), ``trimesh.creation.box``."""
    import trimesh

    tm = trimesh.creation.box(extents=np.asarray(extents, float))
    return Mesh(vertices=np.asarray(tm.vertices) + np.asarray(center, float), faces=np.asarray(tm.faces))


def quad(
    size: tuple[float, float] = (1.0, 1.0),
    center: tuple[float, float, float] = (0.0, 0.0, 0.0),
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0),
    divisions: int = 1,
) -> Mesh:
    """A flat rectangle of ``size`` centred at ``center``, facing ``normal`` (its front side),
    split into ``divisions``² squares of two triangles each. Its texture coordinates ``uv`` run
    from (0, 0) to (1, 1) over the rectangle: ``u`` along ``helper × normal`` (``helper`` the y
    axis, or the x axis for a normal near y), ``v`` along ``normal × u``."""
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
    uv = np.stack([gu.reshape(-1) / size[0] + 0.5, gv.reshape(-1) / size[1] + 0.5], axis=-1)
    return Mesh(vertices=verts, faces=np.asarray(faces), uv=uv)
