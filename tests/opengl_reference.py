"""Real OpenGL as a reference: Mesa's software rasterizer (llvmpipe) through OSMesa and PyOpenGL.

Renders a diffshade :class:`~diffshade.Scene` the way an OpenGL program would, into a 32-bit
float framebuffer (so the comparison is not limited by 8-bit quantisation; colours are still
clamped where OpenGL clamps them, ``GL_CLAMP_VERTEX_COLOR`` and ``GL_CLAMP_FRAGMENT_COLOR`` on):

- flat and Gouraud shading: the fixed-function pipeline (``glLight``, ``glMaterial``,
  ``glLightModel``, ``glFog``, ``glShadeModel``), which lights vertices and clamps per vertex;
  flat shading takes the provoking (last) vertex;
- Phong shading: a GLSL per-fragment shader written from docs/model.md (OpenGL has no
  per-fragment lighting of its own), with the scene's options.

Used by tests/test_opengl_reference.py and benchmarks/compare_opengl.py. Needs the Debian
package ``libosmesa6`` and ``pip install PyOpenGL``; :func:`unavailable` says what is missing.
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

MAX_LIGHTS = 8  # fixed-function OpenGL's GL_MAX_LIGHTS


def unavailable() -> str | None:
    """None if Mesa's OSMesa and PyOpenGL can be used, else what is missing."""
    if os.environ.get("PYOPENGL_PLATFORM") != "osmesa":
        return f"PYOPENGL_PLATFORM is {os.environ.get('PYOPENGL_PLATFORM')!r}, not 'osmesa'"
    try:
        from OpenGL import osmesa  # noqa: F401
    except ImportError as exc:
        return f"PyOpenGL is not installed ({exc}): pip install PyOpenGL"
    except Exception as exc:  # PyOpenGL raises its own errors when libOSMesa is missing
        return f"Mesa's OSMesa library could not be loaded ({type(exc).__name__}: {exc}): apt-get install libosmesa6"
    try:
        _Context.get(4, 4)
    except Exception as exc:
        return f"an OSMesa context could not be created ({type(exc).__name__}: {exc})"
    return None


class _Context:
    """One OSMesa context with a float framebuffer object of the largest size asked so far."""

    _inst = None

    @classmethod
    def get(cls, w, h):
        if cls._inst is None:
            cls._inst = cls()
        cls._inst._ensure(w, h)
        return cls._inst

    def __init__(self):
        from OpenGL import GL as gl
        from OpenGL import arrays, osmesa

        self.gl = gl
        self.ctx = osmesa.OSMesaCreateContextExt(osmesa.OSMESA_RGBA, 24, 0, 0, None)
        if not self.ctx:
            raise RuntimeError("OSMesaCreateContextExt failed")
        self._buf = arrays.GLubyteArray.zeros((1, 1, 4))
        if not osmesa.OSMesaMakeCurrent(self.ctx, self._buf, gl.GL_UNSIGNED_BYTE, 1, 1):
            raise RuntimeError("OSMesaMakeCurrent failed")
        self.size = (0, 0)
        self.fbo = None
        self.version = gl.glGetString(gl.GL_VERSION).decode()
        self.renderer = gl.glGetString(gl.GL_RENDERER).decode()
        self._programs = {}

    def _ensure(self, w, h):
        if (w, h) == self.size:
            return
        gl = self.gl
        if self.fbo is not None:
            gl.glDeleteFramebuffers(1, [self.fbo])
            gl.glDeleteRenderbuffers(2, self.rbs)
        self.fbo = gl.glGenFramebuffers(1)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        self.rbs = gl.glGenRenderbuffers(2)
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, self.rbs[0])
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_RGBA32F, w, h)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_COLOR_ATTACHMENT0, gl.GL_RENDERBUFFER, self.rbs[0])
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, self.rbs[1])
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_DEPTH_COMPONENT32F, w, h)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_DEPTH_ATTACHMENT, gl.GL_RENDERBUFFER, self.rbs[1])
        if gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER) != gl.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError("the float framebuffer is incomplete")
        self.size = (w, h)

    def program(self, defines: str):
        if defines not in self._programs:
            from OpenGL.GL import shaders

            gl = self.gl
            vs = shaders.compileShader(_VERTEX, gl.GL_VERTEX_SHADER)
            fs = shaders.compileShader(defines + _FRAGMENT, gl.GL_FRAGMENT_SHADER)
            self._programs[defines] = shaders.compileProgram(vs, fs, validate=False)
        return self._programs[defines]


def _f32(x):
    return np.ascontiguousarray(np.asarray(x, np.float32))


def _rgba(c, a=1.0):
    c = np.broadcast_to(np.asarray(c, np.float64), (3,))
    return _f32([c[0], c[1], c[2], a])


def _lights(scene, opts, view):
    """Every light in eye space: dicts of position (x, y, z, w), spot axis, cutoff, exponent, edge,
    attenuation and the diffuse, specular and ambient colours (OpenGL's GL_DIFFUSE, GL_SPECULAR,
    GL_AMBIENT)."""
    out = []
    R, t = view[:3, :3], view[:3, 3]
    a = lambda x: np.asarray(x, np.float64)  # noqa: E731
    for kind in ("directional", "point", "spot"):
        L = getattr(scene, kind)
        for i in range(L.count):
            col = a(L.color[i])
            spec = col if L.specular is None else a(L.specular[i])
            amb = a(L.ambient[i]) if opts.per_light_ambient else np.zeros(3)
            d = {
                "diffuse": col,
                "specular": spec,
                "ambient": amb,
                "att": np.array([1.0, 0.0, 0.0]),
                "axis": np.array([0.0, 0.0, -1.0]),
                "cutoff": 180.0,
                "exponent": 0.0,
                "edge": 0.0,
            }
            if kind == "directional":
                d["pos"] = np.r_[R @ -a(L.direction[i]), 0.0]
            else:
                d["pos"] = np.r_[R @ a(L.position[i]) + t, 1.0]
                d["att"] = a(L.attenuation[i])
            if kind == "spot":
                d.update(
                    axis=R @ a(L.axis[i]),
                    cutoff=float(L.cutoff[i]),
                    exponent=float(L.exponent[i]),
                    edge=float(L.edge[i]),
                )
            out.append(d)
    if scene.area.count or scene.multi_lobe.count:
        raise ValueError("OpenGL reference: area and multi-lobe lights have no OpenGL counterpart")
    if len(out) > MAX_LIGHTS:
        raise ValueError(f"OpenGL reference: at most {MAX_LIGHTS} lights")
    return out


def _flat(opts):
    """The render options as the scene file's flat keys (``opts.keys()``), read as attributes; a
    key of a group that is off takes diffshade's default (``clamp_at``, ``fog_distance``)."""
    return SimpleNamespace(**{"clamp_at": "pixel", "fog_distance": "euclidean", **opts.keys()})


def render(scene, opts, polygons=None):
    """``(image [H, W, 3] float64, covered [H, W] bool)`` of ``scene`` by Mesa's OpenGL, rows from
    the top as diffshade's. ``polygons``: the mesh's faces as the file has them (lists of vertex
    indices, more than 3 for a polygon), each drawn as a ``GL_TRIANGLE_FAN``, in place of
    ``scene.mesh.faces``."""
    opts = _flat(opts)
    cam = scene.camera
    w, h = cam.width, cam.height
    c = _Context.get(w, h)
    gl = c.gl
    view = np.asarray(cam.view_matrix(), np.float64)
    proj = np.asarray(cam.projection_matrix(), np.float64)
    V = np.asarray(scene.mesh.vertices, np.float64)
    F = np.asarray(scene.mesh.faces)
    N = np.asarray(scene.mesh.vertex_normals(), np.float64)
    corners = F.reshape(-1) if polygons is None else np.concatenate([np.asarray(p) for p in polygons])
    # (face-major corners: the provoking vertex is each face's last)
    pos, nrm = _f32(V[corners]), _f32(N[corners])
    maps = scene.material.maps()
    uvs = _f32(np.asarray(scene.mesh.uv, np.float64)[corners]) if maps else None
    if scene.mesh.material_ids is not None and len(scene.materials):
        raise ValueError("OpenGL reference: one material per scene")
    if (
        opts.transparency
        or opts.shadows
        or opts.shadow_rays
        or opts.ray_depth
        or opts.transmission
        or opts.fresnel != "none"
    ):
        raise ValueError("OpenGL reference: no transparency, shadows, rays, transmission or Fresnel")
    bg = np.asarray(scene.background, np.float64)

    gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, c.fbo)
    gl.glViewport(0, 0, w, h)
    gl.glClampColor(gl.GL_CLAMP_VERTEX_COLOR, gl.GL_TRUE)
    gl.glClampColor(gl.GL_CLAMP_FRAGMENT_COLOR, gl.GL_TRUE if opts.clamp else gl.GL_FALSE)
    gl.glClampColor(gl.GL_CLAMP_READ_COLOR, gl.GL_FALSE)
    gl.glClearColor(float(bg[0]), float(bg[1]), float(bg[2]), 0.0)
    gl.glClearDepth(1.0)
    gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
    gl.glEnable(gl.GL_DEPTH_TEST)
    gl.glDepthFunc(gl.GL_LESS)
    if opts.cull == "none":
        gl.glDisable(gl.GL_CULL_FACE)
    else:  # counter-clockwise is the front (glFrontFace's default), as in diffshade
        gl.glEnable(gl.GL_CULL_FACE)
        gl.glCullFace(gl.GL_BACK if opts.cull == "back" else gl.GL_FRONT)
    gl.glMatrixMode(gl.GL_PROJECTION)
    gl.glLoadMatrixf(_f32(proj.T))
    gl.glMatrixMode(gl.GL_MODELVIEW)
    gl.glLoadMatrixf(_f32(view.T))
    lights = _lights(scene, opts, view)
    front = scene.material
    back = scene.back_material if scene.back_material is not None else front  # lights back faces when two-sided

    if opts.shading == "phong":
        _phong_program(c, scene, opts, lights, front, back, view)
    else:
        _fixed_function(gl, scene, opts, lights, front, back)
    textures = _bind_textures(gl, scene, opts, maps)
    if maps:
        gl.glEnableClientState(gl.GL_TEXTURE_COORD_ARRAY)
        gl.glTexCoordPointer(2, gl.GL_FLOAT, 0, uvs)
    gl.glEnableClientState(gl.GL_VERTEX_ARRAY)
    gl.glEnableClientState(gl.GL_NORMAL_ARRAY)
    gl.glVertexPointer(3, gl.GL_FLOAT, 0, pos)
    gl.glNormalPointer(gl.GL_FLOAT, 0, nrm)
    if polygons is None:
        gl.glDrawArrays(gl.GL_TRIANGLES, 0, len(corners))
    else:  # each polygon a fan; with the last-vertex convention triangle i takes corner i + 2
        sizes = np.asarray([len(p) for p in polygons])
        for first, n in zip(np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes):
            gl.glDrawArrays(gl.GL_TRIANGLE_FAN, int(first), int(n))
    gl.glDisableClientState(gl.GL_VERTEX_ARRAY)
    gl.glDisableClientState(gl.GL_NORMAL_ARRAY)
    gl.glDisableClientState(gl.GL_TEXTURE_COORD_ARRAY)
    for unit in (1, 0):
        gl.glActiveTexture(gl.GL_TEXTURE0 + unit)
        gl.glDisable(gl.GL_TEXTURE_2D)
    if textures:
        gl.glDeleteTextures(textures)
    gl.glUseProgram(0)
    gl.glFinish()
    px = np.asarray(gl.glReadPixels(0, 0, w, h, gl.GL_RGBA, gl.GL_FLOAT), np.float64).reshape(h, w, 4)[::-1]
    return px[..., :3].copy(), px[..., 3] > 0.5


def _fixed_function(gl, scene, opts, lights, front, back):
    if opts.specular not in ("blinn", "none"):
        raise ValueError("OpenGL reference: the fixed-function specular term is Blinn-Phong's")
    if opts.shading == "flat" and opts.flat_source != "provoking":
        raise ValueError("OpenGL reference: flat shading takes the provoking vertex's colour")
    if opts.clamp is False or opts.clamp_at != "vertex":
        raise ValueError("OpenGL reference: the fixed function clamps each vertex's colour")
    if opts.spot_edge != "hard" or opts.interpolation != "perspective":
        raise ValueError("OpenGL reference: hard spot cutoffs and perspective-correct interpolation only")
    gl.glEnable(gl.GL_LIGHTING)
    gl.glEnable(gl.GL_NORMALIZE)
    gl.glShadeModel(gl.GL_FLAT if opts.shading == "flat" else gl.GL_SMOOTH)
    gl.glProvokingVertex(gl.GL_LAST_VERTEX_CONVENTION)
    ga = np.asarray(scene.ambient_light, np.float64) if opts.ambient else np.zeros(3)
    gl.glLightModelfv(gl.GL_LIGHT_MODEL_AMBIENT, _rgba(ga))
    gl.glLightModeli(gl.GL_LIGHT_MODEL_LOCAL_VIEWER, gl.GL_TRUE if opts.viewer == "local" else gl.GL_FALSE)
    gl.glLightModeli(gl.GL_LIGHT_MODEL_TWO_SIDE, gl.GL_TRUE if opts.two_sided else gl.GL_FALSE)
    gl.glLightModeli(
        gl.GL_LIGHT_MODEL_COLOR_CONTROL,
        gl.GL_SEPARATE_SPECULAR_COLOR if opts.color_sum == "separate" else gl.GL_SINGLE_COLOR,
    )
    for side, m in ((gl.GL_FRONT, front), (gl.GL_BACK, back)):
        gl.glMaterialfv(side, gl.GL_EMISSION, _rgba(m.emission if opts.emission else 0.0))
        gl.glMaterialfv(side, gl.GL_AMBIENT, _rgba(m.ambient))
        gl.glMaterialfv(side, gl.GL_DIFFUSE, _rgba(m.diffuse if opts.diffuse else 0.0))
        gl.glMaterialfv(side, gl.GL_SPECULAR, _rgba(m.specular if opts.specular != "none" else 0.0))
        gl.glMaterialf(side, gl.GL_SHININESS, float(m.shininess))
    for i in range(MAX_LIGHTS):
        gl.glDisable(gl.GL_LIGHT0 + i)
    for i, L in enumerate(lights):
        li = gl.GL_LIGHT0 + i
        gl.glEnable(li)
        gl.glLightfv(li, gl.GL_AMBIENT, _rgba(L["ambient"]))
        gl.glLightfv(li, gl.GL_DIFFUSE, _rgba(L["diffuse"]))
        gl.glLightfv(li, gl.GL_SPECULAR, _rgba(L["specular"]))
        # positions and axes are given in eye space: load the identity first
        gl.glPushMatrix()
        gl.glLoadIdentity()
        gl.glLightfv(li, gl.GL_POSITION, _f32(L["pos"]))
        gl.glLightfv(li, gl.GL_SPOT_DIRECTION, _f32(L["axis"]))
        gl.glPopMatrix()
        gl.glLightf(li, gl.GL_SPOT_CUTOFF, float(L["cutoff"]))
        gl.glLightf(li, gl.GL_SPOT_EXPONENT, float(L["exponent"]))
        gl.glLightf(li, gl.GL_CONSTANT_ATTENUATION, float(L["att"][0]))
        gl.glLightf(li, gl.GL_LINEAR_ATTENUATION, float(L["att"][1]))
        gl.glLightf(li, gl.GL_QUADRATIC_ATTENUATION, float(L["att"][2]))
    if opts.fog != "none":
        if opts.fog_distance != "depth":
            raise ValueError("OpenGL reference: fixed-function fog is by eye-space depth")
        gl.glEnable(gl.GL_FOG)
        gl.glFogi(gl.GL_FOG_MODE, {"linear": gl.GL_LINEAR, "exp": gl.GL_EXP, "exp2": gl.GL_EXP2}[opts.fog])
        gl.glFogf(gl.GL_FOG_START, float(scene.fog.start))
        gl.glFogf(gl.GL_FOG_END, float(scene.fog.end))
        gl.glFogf(gl.GL_FOG_DENSITY, float(scene.fog.density))
        gl.glFogfv(gl.GL_FOG_COLOR, _rgba(scene.fog.color))
        gl.glHint(gl.GL_FOG_HINT, gl.GL_NICEST)
    else:
        gl.glDisable(gl.GL_FOG)


_VERTEX = """
#version 120
varying vec3 p_eye;
varying vec3 n_eye;
varying vec2 uv;
void main() {
    uv = gl_MultiTexCoord0.xy;
    p_eye = (gl_ModelViewMatrix * gl_Vertex).xyz;
    n_eye = gl_NormalMatrix * gl_Normal;
    gl_Position = gl_ProjectionMatrix * (gl_ModelViewMatrix * gl_Vertex);
}
"""

_FRAGMENT = """
varying vec3 p_eye;
varying vec3 n_eye;
varying vec2 uv;
uniform sampler2D diffuse_tex;
uniform sampler2D specular_tex;
uniform int n_lights;
uniform vec4 l_pos[8];
uniform vec3 l_diffuse[8];
uniform vec3 l_specular[8];
uniform vec3 l_ambient[8];
uniform vec3 l_att[8];
uniform vec3 l_axis[8];
uniform float l_cutoff[8];
uniform float l_exponent[8];
uniform float l_edge[8];
uniform vec3 m_emission[2];
uniform vec3 m_ambient[2];
uniform vec3 m_diffuse[2];
uniform vec3 m_specular[2];
uniform float m_shininess[2];
uniform vec3 ambient_light;
uniform vec3 fog_color;
uniform vec3 fog_params; // start, end, density

float spow(float x, float m) { return x > 0.0 ? pow(x, m) : 0.0; }

void main() {
    int side = 0;
    vec3 n = normalize(n_eye);
#ifdef TWO_SIDED
    if (!gl_FrontFacing) { n = -n; side = BACK_SIDE; }
#endif
#ifdef INFINITE_VIEWER
    vec3 v = vec3(0.0, 0.0, 1.0);
#else
    vec3 v = normalize(-p_eye);
#endif
    vec3 c = vec3(0.0), cs = vec3(0.0);  // the primary colour, the specular (secondary) one
    vec3 ka = m_ambient[side], kd = m_diffuse[side], ks = m_specular[side];
#ifdef DIFFUSE_MAP
    ka *= texture2D(diffuse_tex, uv).rgb;
    kd *= texture2D(diffuse_tex, uv).rgb;
#endif
#ifdef SPECULAR_MAP
    ks *= texture2D(specular_tex, uv).rgb;
#endif
#ifdef AMBIENT
    c += ka * ambient_light;
#endif
#ifdef EMISSION
    c += m_emission[side];
#endif
    for (int i = 0; i < n_lights; ++i) {
        vec3 l;
        float f = 1.0;
        if (l_pos[i].w == 0.0) {
            l = normalize(l_pos[i].xyz);
        } else {
            vec3 L = l_pos[i].xyz - p_eye;
            float d = length(L);
            l = L / d;
            f = 1.0 / (l_att[i].x + l_att[i].y * d + l_att[i].z * d * d);
            if (l_cutoff[i] <= 90.0) {
                float cc = dot(-l, normalize(l_axis[i]));
                float cos_cut = cos(radians(l_cutoff[i]));
                float lobe = spow(cc, l_exponent[i]);
#ifdef SMOOTH_EDGE
                float cos_in = cos(radians(max(l_cutoff[i] - l_edge[i], 0.0)));
                float t = cos_in > cos_cut ? clamp((cc - cos_cut) / (cos_in - cos_cut), 0.0, 1.0) : (cc >= cos_cut ? 1.0 : 0.0);
                f *= lobe * t * t * (3.0 - 2.0 * t);
#else
                f *= cc >= cos_cut ? lobe : 0.0;
#endif
            }
        }
        float ndl = dot(n, l);
        vec3 term = vec3(0.0);
#ifdef PER_LIGHT_AMBIENT
        term += ka * l_ambient[i];
#endif
#ifdef DIFFUSE
        term += l_diffuse[i] * kd * max(ndl, 0.0);
#endif
        vec3 sterm = vec3(0.0);
#ifdef SPECULAR_PHONG
        if (ndl > 0.0) sterm += l_specular[i] * ks * spow(dot(v, 2.0 * ndl * n - l), m_shininess[side]);
#endif
#ifdef SPECULAR_BLINN
        if (ndl > 0.0) sterm += l_specular[i] * ks * spow(dot(n, normalize(l + v)), m_shininess[side]);
#endif
        c += f * term;
        cs += f * sterm;
    }
#ifdef MODULATE
    // GL_MODULATE per fragment: the lit colour clamped, then times the texel; the separate
    // specular colour clamped apart and added unmodulated
    vec3 T = texture2D(diffuse_tex, uv).rgb;
#ifdef SEPARATE
    c = clamp(c, 0.0, 1.0) * T + clamp(cs, 0.0, 1.0);
#else
    c = clamp(c + cs, 0.0, 1.0) * T;
#endif
#else
    c += cs;
#ifdef CLAMP
    c = clamp(c, 0.0, 1.0);
#endif
#endif
#ifdef FOG
#ifdef FOG_DEPTH
    float z = -p_eye.z;
#else
    float z = length(p_eye);
#endif
#if FOG == 1
    float ff = fog_params.y > fog_params.x ? clamp((fog_params.y - z) / (fog_params.y - fog_params.x), 0.0, 1.0) : (z <= fog_params.y ? 1.0 : 0.0);
#elif FOG == 2
    float ff = exp(-fog_params.z * z);
#else
    float ff = exp(-(fog_params.z * z) * (fog_params.z * z));
#endif
    c = ff * c + (1.0 - ff) * fog_color;
#endif
    gl_FragColor = vec4(c, 1.0);
}
"""


def _phong_program(c, scene, opts, lights, front, back, view):
    gl = c.gl
    gl.glDisable(gl.GL_LIGHTING)
    gl.glDisable(gl.GL_FOG)
    defs = ["#version 120"]
    for flag, on in (
        ("TWO_SIDED", opts.two_sided),
        ("INFINITE_VIEWER", opts.viewer == "infinite"),
        ("AMBIENT", opts.ambient),
        ("EMISSION", opts.emission),
        ("PER_LIGHT_AMBIENT", opts.per_light_ambient),
        ("DIFFUSE", opts.diffuse),
        ("SPECULAR_PHONG", opts.specular == "phong"),
        ("SPECULAR_BLINN", opts.specular == "blinn"),
        ("SMOOTH_EDGE", opts.spot_edge == "smooth"),
        ("CLAMP", opts.clamp),
        ("FOG_DEPTH", opts.fog_distance == "depth"),
        ("MODULATE", _modulates(opts, front)),
        ("SEPARATE", opts.color_sum == "separate"),
        ("DIFFUSE_MAP", front.diffuse_map is not None and not _modulates(opts, front)),
        ("SPECULAR_MAP", front.specular_map is not None and not _modulates(opts, front)),
    ):
        if on:
            defs.append(f"#define {flag}")
    defs.append("#define BACK_SIDE 1")
    if opts.fog != "none":
        defs.append(f"#define FOG {['linear', 'exp', 'exp2'].index(opts.fog) + 1}")
    prog = c.program("\n".join(defs) + "\n")
    gl.glUseProgram(prog)
    u = lambda name: gl.glGetUniformLocation(prog, name)  # noqa: E731
    n = len(lights)
    gl.glUniform1i(u("n_lights"), n)
    if n:
        gl.glUniform4fv(u("l_pos"), n, _f32([L["pos"] for L in lights]))
        for key in ("diffuse", "specular", "ambient", "att", "axis"):
            gl.glUniform3fv(u(f"l_{key}"), n, _f32([L[key] for L in lights]))
        for key in ("cutoff", "exponent", "edge"):
            gl.glUniform1fv(u(f"l_{key}"), n, _f32([L[key] for L in lights]))
    for key in ("emission", "ambient", "diffuse", "specular"):
        gl.glUniform3fv(
            u(f"m_{key}"), 2, _f32([np.broadcast_to(np.asarray(getattr(m, key)), (3,)) for m in (front, back)])
        )
    gl.glUniform1fv(u("m_shininess"), 2, _f32([float(front.shininess), float(back.shininess)]))
    gl.glUniform1i(u("diffuse_tex"), 0)
    gl.glUniform1i(u("specular_tex"), 1)
    gl.glUniform3fv(u("ambient_light"), 1, _f32(scene.ambient_light))
    gl.glUniform3fv(u("fog_color"), 1, _f32(scene.fog.color))
    gl.glUniform3fv(u("fog_params"), 1, _f32([float(scene.fog.start), float(scene.fog.end), float(scene.fog.density)]))


def _modulates(opts, m) -> bool:
    """Whether the GLSL program applies the diffuse map as ``GL_MODULATE`` (diffshade's lit maps:
    Phong shading clamped per vertex): then one map on the emission, ambient and diffuse colours
    (and the specular with ``GL_SINGLE_COLOR``), none on the specular with the separate colour."""
    if not (opts.clamp and opts.clamp_at == "vertex" and m.diffuse_map is not None):
        return False
    maps = m.maps()  # (the sharing fields given the first's map: flattening copied them)
    t = maps["diffuse"]
    want = {"emission": t, "ambient": t, "diffuse": t, "specular": t if opts.color_sum == "single" else None}
    if any(maps.get(f) is not w for f, w in want.items()):
        raise ValueError(
            "OpenGL reference: GL_MODULATE is one map on the emission, ambient and diffuse colours (and the "
            "specular with the single colour sum)"
        )
    return True


def _bind_textures(gl, scene, opts, maps):
    """The material's maps as float textures (unit 0: diffuse, 1: specular), rows flipped (OpenGL's
    row 0 is t = 0), mipmapped by ``glGenerateMipmap`` where the filter is trilinear. The fixed
    function modulates the primary colour (``GL_MODULATE``: emission, ambient and diffuse), so
    there the scene must have a diffuse map only, no emission, and the specular colour apart."""
    if not maps:
        return []
    m = scene.material
    if opts.shading == "phong" and _modulates(opts, m):
        pass
    elif set(maps) - {"diffuse", "ambient", "specular"} or (m.ambient_map is not None):
        raise ValueError("OpenGL reference: diffuse (with its ambient) and specular maps only")
    if opts.shading != "phong" and (
        m.specular_map is not None or opts.emission or opts.color_sum != "separate" or scene.back_material
    ):
        raise ValueError(
            "OpenGL reference: the fixed function modulates the primary colour: a diffuse map only, no emission, separate specular"
        )
    names = []
    for unit, tex in ((0, m.diffuse_map), (1, m.specular_map)):
        if tex is None:
            continue
        t = np.asarray(tex.texels, np.float64)[::-1]
        h, w, ch = t.shape
        if ch == 1:
            t = np.repeat(t, 3, axis=-1)
        gl.glActiveTexture(gl.GL_TEXTURE0 + unit)
        name = gl.glGenTextures(1)
        names.append(name)
        gl.glBindTexture(gl.GL_TEXTURE_2D, name)
        gl.glPixelStorei(gl.GL_UNPACK_ALIGNMENT, 1)
        if tex.mipmaps in ("srgb8", "llvmpipe"):  # 8-bit sRGB codes (the texels must be such codes' values)
            codes = np.round(_srgb_encode(np.clip(t, 0.0, 1.0)) * 255.0)
            if np.abs(_srgb_decode(codes / 255.0) - t).max() > 1e-6:
                raise ValueError("OpenGL reference: a map with mipmaps='srgb8' must hold 8-bit sRGB codes' values")
            data = np.ascontiguousarray(codes.astype(np.uint8))
            gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_SRGB8, w, h, 0, gl.GL_RGB, gl.GL_UNSIGNED_BYTE, data)
        else:
            gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_RGB32F, w, h, 0, gl.GL_RGB, gl.GL_FLOAT, _f32(t))
        trilinear = tex.filter == "trilinear"
        if trilinear:
            gl.glGenerateMipmap(gl.GL_TEXTURE_2D)
        gl.glTexParameteri(
            gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR_MIPMAP_LINEAR if trilinear else gl.GL_LINEAR
        )
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR)
        wrap = gl.GL_REPEAT if tex.wrap == "repeat" else gl.GL_CLAMP_TO_EDGE
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_WRAP_S, wrap)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_WRAP_T, wrap)
        if opts.shading != "phong":
            gl.glEnable(gl.GL_TEXTURE_2D)
            gl.glTexEnvi(gl.GL_TEXTURE_ENV, gl.GL_TEXTURE_ENV_MODE, gl.GL_MODULATE)
    gl.glActiveTexture(gl.GL_TEXTURE0)
    return names


def _srgb_encode(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)


def _srgb_decode(c):
    return np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)


def compare(img, covered, ref, ref_covered, margin: int = 0):
    """Median and 99th percentile of ``|img - ref|`` over the pixels both cover (at least
    ``margin`` pixels inside both coverages: silhouette pixels are a coverage question), and the
    coverage agreement (pixels both cover over pixels either covers)."""
    both = covered & ref_covered
    either = covered | ref_covered
    inner = both.copy()
    for dy in range(-margin, margin + 1):
        for dx in range(-margin, margin + 1):
            inner &= np.roll(np.roll(both, dy, 0), dx, 1)
    d = np.abs(img - ref)[inner].reshape(-1)
    return {
        "median": float(np.median(d)) if d.size else np.nan,
        "p99": float(np.percentile(d, 99)) if d.size else np.nan,
        "max": float(d.max()) if d.size else np.nan,
        "pixels": int(inner.sum()),
        "coverage": float(both.sum() / max(either.sum(), 1)),
    }
