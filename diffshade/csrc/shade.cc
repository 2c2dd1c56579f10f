// diffshade native shading kernel (CPU), registered with XLA through jax.ffi: the per-pixel
// (Phong-shaded) local model of diffshade/_lighting.py for one layer and one material, from the
// fragments to the final pixel (barycentrics, interpolated normal and position, every light's
// terms, clamp, fog, background and the camera's gain) in one pass over the pixels; or, for
// Gouraud shading, the vertices' colours (lit by the JAX stages) interpolated, fogged and
// clamped; with texture maps of the material's colours (and, Phong, its shininess), sampled as
// diffshade/_texture.py samples them. The pure-JAX stages stay the reference and, by default,
// the differentiated path: diffshade/_fast.py calls this kernel for a render's value, and (within
// ds.kernel_partials) the second one below for the value and its partials along the shading
// numbers; its tests hold both equal to the stages to float32 rounding.
//
// The formulas follow diffshade/_shade.py term by term, with the same guards (double-where
// cases: a zero normal, a light on the surface, 0^m, an empty pixel).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#if defined(__x86_64__)
#include <immintrin.h>
#endif
#include <vector>

#include "parallel.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// Layouts shared with diffshade/_fast.py (kept in step by its constants).
// Per face, kFace floats (built by FaceTable below): the edge functions of
// _raster.py::_face_planes (E_i = c + a x + b y for i = 0..2 at the pixel centre (x, y) in NDC),
// the corners' clip w (w = sum_i b_i w_i at a pixel), the clip-space determinant D, the
// corners' normals (3 x 3; Gouraud: their front colours), their positions (3 x 3), whether the
// face is front-facing (D > 0; 1 or 0), and (Gouraud) the corners' back colours (3 x 3).
constexpr int kFace = 41;
// Per material, kMat floats: emission, ambient, diffuse, specular (3 each), shininess, ior, and
// the other local models' roughness (Cook-Torrance's alpha, Ward's alpha_x), roughness_y (Ward's
// alpha_y), diffuse_roughness (Oren-Nayar's sigma) and tangent (3, Ward's).
constexpr int kMat = 20;
// The scene's numbers: two materials (front, back), the ambient light (3), the eye (3), the
// eye-space +z axis in world coordinates (3), the fog's colour (3), start, end, density, the
// background (3), the camera's gain (3).
constexpr int kParams = 2 * kMat + 3 + 3 + 3 + 6 + 3 + 3;
// Per light, kLight floats: kind (0 directional, 1 point, 2 spot), colour (3), ambient (3),
// specular colour (3), whether it has one, the unit vector to it (directional) or its position
// (3), attenuation (3), the spot's unit axis (3), cos of its cutoff, cos of the inner edge, its
// exponent, whether the edge is smooth.
constexpr int kLight = 24;

// exp, log and x^m of a block's floats (csrc/math_lanes.h: Cephes' expf and logf, a polynomial
// after range reduction, within 2 ulp of libm's on their range here), W lanes at a time in GCC's
// vector extensions. libm's are calls, one value at a time (the all-terms render spent most of
// its time in them); left to the auto-vectoriser, straight-line scalar versions vectorised for
// SSE2 but not for AVX2, where GCC split Exp's clamp into paths and a float-to-int conversion on
// one of them kept the loop scalar. With the per-light terms compiled for AVX2 the all-terms
// render at 512² then took 20.5 ms of shading, against 13.3 ms for SSE2; this way 11.8-12.5 ms
// for the whole render, against 16.5-17.9 ms. Eight lanes for AVX2, four otherwise (eight split
// into SSE2 pairs were 5-15 % slower). The lane functions are always inlined into MapLanes, which
// takes and passes no vectors: its AVX2 and default versions agree on how arguments pass.
#pragma GCC diagnostic ignored "-Wpsabi"  // (the note that such vectors pass differently with AVX)
enum LaneOp { kExp, kLog, kPow };
namespace lanes4 {
constexpr int W = 4;
typedef float F __attribute__((vector_size(16)));
typedef int32_t I __attribute__((vector_size(16)));
#include "math_lanes.h"
}  // namespace lanes4
namespace lanes8 {
constexpr int W = 8;
typedef float F __attribute__((vector_size(32)));
typedef int32_t I __attribute__((vector_size(32)));
#include "math_lanes.h"
}  // namespace lanes8

// out[q] = op(x[q]) for q < m (kPow: x[q]^e[q] with e_step 1, x[q]^e[0] with 0): x, e and out are
// arrays of kBlock (a multiple of 8) floats, and the lanes from m to the next multiple of the
// width are computed from what they hold and written (no pixel's). out may be x.
#if DIFFSHADE_HAS_CLONES
__attribute__((target("avx2"))) void MapLanes(int op, const float* x, const float* e, int e_step, float* out, int m) {
  lanes8::Map(op, x, e, e_step, out, m);
}
__attribute__((target("default"))) void MapLanes(int op, const float* x, const float* e, int e_step, float* out,
                                                 int m) {
  lanes4::Map(op, x, e, e_step, out, m);
}
#else
void MapLanes(int op, const float* x, const float* e, int e_step, float* out, int m) {
  lanes4::Map(op, x, e, e_step, out, m);
}
#endif
inline void ExpN(const float* x, float* out, int m) { MapLanes(kExp, x, nullptr, 0, out, m); }  // e^x, x clamped to [-87.3, 88.3]
inline void LogN(const float* x, float* out, int m) { MapLanes(kLog, x, nullptr, 0, out, m); }  // x positive and normal
// x^e with 0^e = 0, and 0 where e log x is below the log of the smallest normal float
// (_shade.safe_pow)
inline void SafePowN(const float* x, const float* e, int e_step, float* out, int m) {
  MapLanes(kPow, x, e, e_step, out, m);
}

inline float Radial(float d, const float* a) {  // _shade.radial_attenuation
  const float kEps = 2.2737368e-13f;  // cbrt(FLT_MIN)
  const float den = a[0] + a[1] * d + a[2] * d * d;
  return den > kEps ? 1.0f / den : 1.0f / kEps;
}

inline float Clip01(float x) { return std::min(std::max(x, 0.0f), 1.0f); }

inline float Schlick(float c, float ior) {  // _shade.fresnel_schlick
  const float r = (ior - 1.0f) / (ior + 1.0f), f0 = r * r;
  const float q = 1.0f - Clip01(c);
  return f0 + (1.0f - f0) * (q * q * q * q * q);
}

inline float Dielectric(float c, float ior) {  // _shade.fresnel_dielectric, branch-free
  const float ci = Clip01(c);
  const float s2 = (1.0f - ci * ci) / (ior * ior);
  const bool tir = s2 >= 1.0f;
  const float ct = std::sqrt(tir ? 0.0f : 1.0f - s2);
  const float rs_den = ci + ior * ct, rp_den = ior * ci + ct;
  const bool ok = !tir && rs_den > 0 && rp_den > 0;
  const float rs = (ci - ior * ct) / (ok ? rs_den : 1.0f), rp = (ior * ci - ct) / (ok ? rp_den : 1.0f);
  return ok ? 0.5f * (rs * rs + rp * rp) : 1.0f;
}

// Static configuration (the FFI attributes).
struct Config {
  int32_t specular;  // 0 none, 1 phong, 2 blinn, 3 beckmann, 4 ggx (Cook-Torrance), 5 ward
  int32_t fresnel;   // 0 none, 1 schlick, 2 dielectric
  int32_t flags;     // bits: emission, ambient, diffuse, per-light ambient, two-sided, infinite viewer,
                     // clamp before fog, clamp after fog, Gouraud (the colours are the vertices'),
                     // Oren-Nayar's diffuse, Cook-Torrance's V-cavity masking (else Smith's)
  int32_t fog;       // 0 none, 1 linear, 2 exp, 3 exp2; +4: by eye-space depth
  bool Flag(int bit) const { return (flags >> bit) & 1; }
};

// Pixels are shaded in blocks of kBlock: the covered ones' points are evaluated into arrays
// (structure of arrays), and each step of the model is then a loop over the block without
// branches or pointer selects, which the compiler vectorises (square roots and divisions four at
// a time; one pixel at a time they were a chain of latencies, 25 ns per pixel).
constexpr int kBlock = 64;
static_assert(kBlock % 8 == 0, "MapLanes works in lanes of up to 8");
constexpr int kMaxMaps = 5;    // distinct maps (emission, ambient, diffuse, specular, shininess)
constexpr int kMaxParts = 4;   // Gouraud: colour parts under a map (the ambient shares the diffuse map)
constexpr int kMaxLevels = 32;

// Texture maps (diffshade/_texture.py), described by the int32 "maps" input
// (_fast.py::_texture_inputs): per material field (emission, ambient, diffuse, specular,
// shininess) its map or -1; the number of Gouraud parts and each part's map; the camera's width
// and height; the number of maps, and per map kMapInts ints: channels, clamp (1) or repeat (0),
// trilinear (1) or bilinear (0), width, height. The "texels" input holds each map's texels (row
// 0 at the top, channels interleaved), one map after the other; the kernel copies them into its
// own scratch, each level with a border of one texel on every side (what a tap beyond the edge
// reads: the other side, repeating, or the edge, clamping; _texture._padded), and builds the
// mipmap pyramids of the trilinear ones (_texture.mip_pyramid) there. With the border, a
// bilinear sample's four taps are two pairs of neighbours in two rows, whatever the wrap.
constexpr int kMapInts = 5;
constexpr int kMapsHeader = 5 + 1 + kMaxParts + 2 + 1;

struct Level {
  int64_t off;  // in the scratch: the first texel of the border (level 0's in the input: Map::given)
  int w, h;     // without the border
  int64_t Stride(int C) const { return (int64_t{w} + 2) * C; }  // a bordered row, in floats
  int64_t Inside(int C) const { return Stride(C) + C; }          // the first texel past the border
};
struct Map {
  int channels, levels;
  bool clamp, trilinear;
  int64_t given;  // level 0's offset in the texels input
  Level lv[kMaxLevels];
  const float* base[kMaxLevels];  // each level's first texel, its border's top-left corner
};
struct Maps {
  int field[5] = {-1, -1, -1, -1, -1};
  int parts = 0, part_map[kMaxParts] = {};
  int count = 0;
  bool derivatives = false;  // a trilinear map needs the coordinates' derivatives
  float sx = 0, sy = 0;      // NDC per pixel step (2 / width, 2 / height)
  Map map[kMaxMaps];
  // per face, face_floats floats (FaceMap::Of's, in Prepare, from the coordinates [V, 2] and
  // Gouraud's parts [parts, 2 (front, back), V, 3]): what FaceMap reads
  const float* faces = nullptr;
  int face_floats = 0;
  bool any() const { return count > 0; }
};

// (what PointsOf writes has room for a run's last vector of eight past the block's end)
constexpr int kRoom = kBlock + 8;
struct Block {
  int64_t pix[kRoom];
  int32_t face[kRoom];  // the face each pixel sees
  float nx[kRoom], ny[kRoom], nz[kRoom];  // unit normal (on the lit side)
  float px[kRoom], py[kRoom], pz[kRoom];  // position
  float vx[kBlock], vy[kBlock], vz[kBlock];  // unit vector to the viewer
  float w[kRoom], back[kRoom];               // clip w; 1 where the back side (material) is lit
  float lx[kBlock], ly[kBlock], lz[kBlock], att[kBlock], ndl[kBlock];
  // the specular term, the fog's factor; a spot light's cosine to its axis and its lobe cos^e
  // (zeroed: MapLanes reads up to a multiple of 8 past a block's last pixel)
  float spec[kBlock] = {}, fog[kBlock] = {}, cs[kBlock] = {}, lobe[kBlock] = {};
  // the diffuse factor (Lambert's (n.l)+ or Oren-Nayar's, times the diffuse switch); the other
  // local models' scratch (zeroed: ExpN reads them in lanes of eight)
  float dif[kBlock] = {}, t0[kBlock] = {}, t1[kBlock] = {}, t2[kBlock] = {};
  float dl0[kBlock] = {}, dl1[kBlock] = {};  // (the partials: the specular's log-derivatives in its roughnesses)
  float col[3][kBlock], base[3][kBlock];
  // the material per pixel (emission, ambient, diffuse, specular, shininess): the side's
  // constants, times the texels where a field has a map
  float ke[3][kBlock], ka[3][kBlock], kd[3][kBlock], ks[3][kBlock], sh[kBlock];
  // texture coordinates and (trilinear) their derivatives per pixel step; each map's sample
  float u[kRoom], v[kRoom], dux[kRoom], dvx[kRoom], duy[kRoom], dvy[kRoom];
  float su[kBlock], sv[kBlock], sd[kBlock] = {};  // a map's wrapped coordinates and level of detail
  float b0[kRoom], b1[kRoom], b2[kRoom];  // the barycentrics
  // a sample's taps (SampleMap): the top-left texel's index in its bordered level and the step
  // down (its row, in floats), the weights; the pixels that blend a second level (their entries,
  // coordinates, levels, weights and samples)
  int32_t ti[kBlock], tdy[kBlock], lvl[kBlock], sel[kBlock];
  float fx[kBlock], fy[kBlock], cu[kBlock], cv[kBlock], cf[kBlock], hi[3][kBlock];
  float tex[kMaxMaps][3][kBlock];
  float part[kMaxParts][3][kRoom];  // Gouraud: each mapped part's interpolated colour
  bool fixed = false;  // PixelMaterial has written the fields that are constant
};

// The pixels shaded: their faces (ids [n], -1 where none) and centres in NDC (xs [width] and
// ys [n / width] in a grid; otherwise xs and ys [n], one per pixel).
struct Pixels {
  const int32_t* ids;
  const float *xs, *ys;
  bool grid;
  int64_t width, n;
};

inline float Pick(float back, float b, float f) { return back > 0 ? b : f; }

// floor(x) for |x| < 2^31, as straight-line code (std::floor is a call into libm on a plain
// x86-64); the callers bound x first, in loops of their own (in one loop with the bounds, GCC's
// AVX2 clones would not vectorise it).
inline float Floor(float x) {
  const float t = static_cast<float>(static_cast<int32_t>(x));
  return t > x ? t - 1.0f : t;
}

// Where n bilinear samples of a map read (_texture._taps: the coordinates u, v wrapped into
// [0, 1] already where repeating; level lv of the map): the top-left tap's index in its bordered
// level, from -1 (the border) to the last texel, and the step to the row below (vectorised).
DIFFSHADE_CLONES void TapsAt(const Map& t, const float* __restrict u, const float* __restrict v,
                             const int32_t* __restrict lv, int n, Block& k) {
  const int C = t.channels, w0 = t.lv[0].w - 1, h0 = t.lv[0].h - 1;
  int32_t* __restrict ti = k.ti;
  int32_t* __restrict tdy = k.tdy;
  float* __restrict fx = k.fx;
  float* __restrict fy = k.fy;
  for (int j = 0; j < n; ++j) {
    const int L = lv[j], W = (w0 >> L) + 1, H = (h0 >> L) + 1;  // (the levels' sizes: w halved, rounding up)
    const float x = u[j] * static_cast<float>(W) - 0.5f, y = (1.0f - v[j]) * static_cast<float>(H) - 0.5f;
    const float x0 = Floor(x), y0 = Floor(y);  // (|x| <= 2 W + 1: u, v in [-1, 2])
    fx[j] = x - x0, fy[j] = y - y0;
    const int ix = std::min(std::max(static_cast<int>(x0), -1), W - 1);
    const int iy = std::min(std::max(static_cast<int>(y0), -1), H - 1);
    tdy[j] = (W + 2) * C;
    ti[j] = (iy + 1) * tdy[j] + (ix + 1) * C;
  }
}

// Four floats from p (a texel's three channels and one float after it, which the scratch's
// slack keeps in bounds), as one vector: GCC's and Clang's vector extension (SSE, or a scalar
// fallback on other targets).
typedef float F4 __attribute__((vector_size(16)));
inline F4 Load4(const float* p) {
  F4 r;
  std::memcpy(&r, p, sizeof(r));
  return r;
}

// Three-channel bilinear samples j to n - 1 (Blend's), as vectors of a texel's channels (the
// fourth lane unused): two loads per row of taps.
inline void BlendFrom(const Map& map, const int32_t* __restrict lv, const Block& k, int j, int n, float (*out)[kBlock]) {
  for (; j < n; ++j) {
    const float* t00 = map.base[lv[j]] + k.ti[j];
    const float* t10 = t00 + k.tdy[j];
    const F4 fx = F4{} + k.fx[j], fy = F4{} + k.fy[j];
    const F4 a0 = Load4(t00), a1 = Load4(t00 + 3), b0 = Load4(t10), b1 = Load4(t10 + 3);
    const F4 top = a0 + fx * (a1 - a0), bottom = b0 + fx * (b1 - b0);
    const F4 s = top + fy * (bottom - top);
    out[0][j] = s[0], out[1][j] = s[1], out[2][j] = s[2];
  }
}
#if DIFFSHADE_HAS_CLONES
// AVX2: eight samples at a time, pixels i and i + 4 in the two halves of one register (the same
// operations on the same numbers: the same bits), their channels then transposed into three
// vectors of eight (one store per channel, not three a pixel: Blend was a quarter of what a map
// added to a 512² Gouraud render).
__attribute__((target("avx2"))) void Blend3(const Map& map, const int32_t* __restrict lv, const Block& k, int n,
                                            float (*out)[kBlock]) {
  int j = 0;
  for (; j + 8 <= n; j += 8) {
    const __m256 fxs = _mm256_loadu_ps(k.fx + j), fys = _mm256_loadu_ps(k.fy + j);
    __m256 s[4];
    for (int i = 0; i < 4; ++i) {
      const float* a = map.base[lv[j + i]] + k.ti[j + i];
      const float* b = map.base[lv[j + i + 4]] + k.ti[j + i + 4];
      const float* a1 = a + k.tdy[j + i];
      const float* b1 = b + k.tdy[j + i + 4];
      const __m256i pick = _mm256_setr_epi32(i, i, i, i, i + 4, i + 4, i + 4, i + 4);
      const __m256 fx = _mm256_permutevar8x32_ps(fxs, pick), fy = _mm256_permutevar8x32_ps(fys, pick);
      const __m256 t0 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(a)), _mm_loadu_ps(b), 1);
      const __m256 t1 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(a + 3)), _mm_loadu_ps(b + 3), 1);
      const __m256 u0 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(a1)), _mm_loadu_ps(b1), 1);
      const __m256 u1 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(a1 + 3)), _mm_loadu_ps(b1 + 3), 1);
      const __m256 top = _mm256_add_ps(t0, _mm256_mul_ps(fx, _mm256_sub_ps(t1, t0)));
      const __m256 bottom = _mm256_add_ps(u0, _mm256_mul_ps(fx, _mm256_sub_ps(u1, u0)));
      s[i] = _mm256_add_ps(top, _mm256_mul_ps(fy, _mm256_sub_ps(bottom, top)));
    }
    const __m256 rg01 = _mm256_unpacklo_ps(s[0], s[1]), b01 = _mm256_unpackhi_ps(s[0], s[1]);
    const __m256 rg23 = _mm256_unpacklo_ps(s[2], s[3]), b23 = _mm256_unpackhi_ps(s[2], s[3]);
    _mm256_storeu_ps(out[0] + j, _mm256_shuffle_ps(rg01, rg23, 0x44));
    _mm256_storeu_ps(out[1] + j, _mm256_shuffle_ps(rg01, rg23, 0xee));
    _mm256_storeu_ps(out[2] + j, _mm256_shuffle_ps(b01, b23, 0x44));
  }
  BlendFrom(map, lv, k, j, n, out);
}
__attribute__((target("default"))) void Blend3(const Map& map, const int32_t* __restrict lv, const Block& k, int n,
                                               float (*out)[kBlock]) {
  BlendFrom(map, lv, k, 0, n, out);
}
#else
void Blend3(const Map& map, const int32_t* __restrict lv, const Block& k, int n, float (*out)[kBlock]) {
  BlendFrom(map, lv, k, 0, n, out);
}
#endif

// The n bilinear samples at the taps of TapsAt (_texture._blend, in its order), three channels
// out (a one-channel map repeated: grey).
DIFFSHADE_CLONES void Blend(const Map& map, const int32_t* __restrict lv, const Block& k, int n,
                            float (*out)[kBlock]) {
  if (map.channels == 3) {
    Blend3(map, lv, k, n, out);
    return;
  }
  for (int j = 0; j < n; ++j) {
    const float* t00 = map.base[lv[j]] + k.ti[j];
    const float* t10 = t00 + k.tdy[j];
    const float fx = k.fx[j], fy = k.fy[j];
    const float top = t00[0] + fx * (t00[1] - t00[0]), bottom = t10[0] + fx * (t10[1] - t10[0]);
    out[0][j] = top + fy * (bottom - top);
  }
  for (int c = 1; c < 3; ++c) std::memcpy(out[c], out[0], n * sizeof(float));
}

// A map sampled at the block's m pixels (_texture.sample_channels; trilinear with
// level_of_detail). In passes without branches (vectorised): the wrapped coordinates and the
// level of detail; every pixel's first level; then the second level of those that blend two.
DIFFSHADE_CLONES void SampleMap(const Map& t, Block& k, int m, float (*out)[kBlock]) {
  const float top = static_cast<float>(t.levels - 1);
  const float w0 = static_cast<float>(t.lv[0].w), h0 = static_cast<float>(t.lv[0].h);
  float* __restrict su = k.su;
  float* __restrict sv = k.sv;
  int32_t* __restrict lvl = k.lvl;
  const float* __restrict u = k.u;
  const float* __restrict v = k.v;
  // (clamping: beyond [-1, 2] both taps read the edge texel, as at -1 or 2; repeating: beyond
  // 2^23 a float is a whole number, as 2^23 is)
  const float bound = t.clamp ? 2.0f : 8388608.0f;
  for (int q = 0; q < m; ++q) {
    su[q] = std::min(std::max(u[q], -bound + (t.clamp ? 1.0f : 0.0f)), bound);
    sv[q] = std::min(std::max(v[q], -bound + (t.clamp ? 1.0f : 0.0f)), bound);
  }
  if (!t.clamp) {
    for (int q = 0; q < m; ++q) su[q] = su[q] - Floor(su[q]), sv[q] = sv[q] - Floor(sv[q]);
  }
  const int last = t.levels - 1;
  int blend = 0;
  if (t.trilinear) {
    float* __restrict sd = k.sd;
    int minified = 0;
    for (int q = 0; q < m; ++q) {  // the footprint's squared length; 1 (level 0) where it is ~0
      const float ax = k.dux[q] * w0, bx = k.dvx[q] * h0, ay = k.duy[q] * w0, by = k.dvy[q] * h0;
      const float r2 = std::max(ax * ax + bx * bx, ay * ay + by * by);
      sd[q] = r2 > 1e-30f ? r2 : 1.0f;
      minified |= sd[q] > 1.0f ? 1 : 0;
    }
    if (minified == 0) {  // (magnified everywhere, as most of a close object's blocks: level 0, as
      for (int q = 0; q < m; ++q) lvl[q] = 0;  // below, where log r2 <= 0 is clamped to 0)
    } else {
      LogN(sd, sd, m);
      for (int q = 0; q < m; ++q) {
        const float lod = 0.5f * (sd[q] * 1.44269504088896341f);
        const float d = std::min(std::max(lod, 0.0f), top);
        lvl[q] = std::min(static_cast<int32_t>(d), last);  // (d >= 0)
        sd[q] = d - static_cast<float>(lvl[q]);
      }
      for (int q = 0; q < m; ++q) {  // (a + 0 (b - a) is a: the pixels with a fraction blend)
        k.sel[blend] = q;
        blend += sd[q] > 0 ? 1 : 0;
      }
    }
  } else {
    for (int q = 0; q < m; ++q) lvl[q] = 0;
  }
  TapsAt(t, su, sv, lvl, m, k);
  Blend(t, lvl, k, m, out);
  if (blend == 0) return;
  for (int j = 0; j < blend; ++j) {
    const int q = k.sel[j];
    k.cu[j] = su[q], k.cv[j] = sv[q], k.cf[j] = k.sd[q], lvl[j] = std::min(lvl[q] + 1, last);
  }
  TapsAt(t, k.cu, k.cv, lvl, blend, k);
  Blend(t, lvl, k, blend, k.hi);
  for (int c = 0; c < 3; ++c) {
    for (int j = 0; j < blend; ++j) {
      const int q = k.sel[j];
      out[c][q] = out[c][q] + k.cf[j] * (k.hi[c][j] - out[c][q]);
    }
  }
}

// The other local models (docs/model.md §2, "The other local models"): diffshade/_local_models.py
// term by term, with its guards; each fills the block's dif (Oren-Nayar) or spec (Cook-Torrance,
// Ward) for one light after AddLight's l, ndl. Their parameters are the lit side's constants (a
// roughness map takes the JAX stages).
constexpr float kPi = 3.14159265358979f;
constexpr float kBeckmannFloor = 1e-4f;  // _local_models.BECKMANN_FLOOR
constexpr float kWardGrazing = 1e-6f;    // _local_models.WARD_GRAZING

inline float NdotV(const Block& k, int q) { return k.nx[q] * k.vx[q] + k.ny[q] * k.vy[q] + k.nz[q] * k.vz[q]; }

// Oren-Nayar's A and B of sigma, and their derivatives in sigma.
inline void OrenNayarAB(float s, float* a, float* b, float* da, float* db) {
  const float s2 = s * s, ea = s2 + 0.33f, eb = s2 + 0.09f;
  *a = 1.0f - 0.5f * s2 / ea, *b = 0.45f * s2 / eb;
  *da = -0.33f * s / (ea * ea), *db = 0.081f * s / (eb * eb);
}

// (l.v - (n.l)(n.v)) / max(n.l, n.v): cos(phi_l - phi_v) sin(alpha) tan(beta), 0 where unseen.
inline float OrenNayarAcross(float ndl, float ndv, float ldv) {
  const float big = std::max(ndl, ndv);
  const float a = ndv > 0 ? std::max(ldv - ndl * ndv, 0.0f) : 0.0f;
  return a / (big > 0 ? big : 1.0f);
}

// The diffuse factor into k.dif: Lambert's (n.l)+ or Oren-Nayar's, times the diffuse switch.
inline void Diffuse(const Config& cfg, const float* front, const float* backm, Block& k, int m) {
  const float on = cfg.Flag(2) ? 1.0f : 0.0f;
  float* __restrict dif = k.dif;
  if (!cfg.Flag(9)) {
    for (int q = 0; q < m; ++q) dif[q] = std::max(k.ndl[q], 0.0f) * on;
    return;
  }
  float af, bf, ab, bb, d0, d1;  // (sigma is the side's constant: A and B once a block)
  OrenNayarAB(front[16], &af, &bf, &d0, &d1);
  OrenNayarAB(backm[16], &ab, &bb, &d0, &d1);
  for (int q = 0; q < m; ++q) {
    const float a = Pick(k.back[q], ab, af), b = Pick(k.back[q], bb, bf);
    const float ndl = k.ndl[q], ndv = NdotV(k, q), ldv = k.lx[q] * k.vx[q] + k.ly[q] * k.vy[q] + k.lz[q] * k.vz[q];
    const float across = OrenNayarAcross(ndl, ndv, ldv);
    dif[q] = (ndl > 0 && std::max(ndl, ndv) > 0 ? ndl * (a + b * across) : 0.0f) * on;
  }
}

// G1(w)/(n.w) of Smith's masking (GGX exact; Beckmann by Walter et al.'s rational form) and its
// logarithm's derivative in alpha.
inline float SmithGgx(float c, float a2) { return 2.0f / (c + std::sqrt(a2 + (1.0f - a2) * c * c)); }
inline float SmithGgxDlog(float c, float alpha) {
  const float a2 = alpha * alpha, r = std::sqrt(a2 + (1.0f - a2) * c * c);
  return -(alpha * (1.0f - c * c) / r) / (c + r);
}
inline float SmithBeckmann(float c, float alpha, float* dlog) {
  const float s2 = std::max(1.0f - c * c, 0.0f);
  const bool near = !(s2 > 0);
  const float s = std::sqrt(s2 > 0 ? s2 : 1.0f);
  const float a = c / (alpha * s);
  const float num = 3.535f + 2.181f * a, den = 1.0f + 2.276f * a + 2.577f * a * a;
  const float rational = num / (den * alpha * s);
  const bool one = near || a >= 1.6f;
  *dlog = one ? 0.0f : (2.181f / num - (2.276f + 5.154f * a) / den) * (-a / alpha) - 1.0f / alpha;
  return one ? (c > 0 ? 1.0f / c : 0.0f) : rational;
}

// Cook-Torrance's D G F / (4 (n.l)(n.v)) (n.l)+ into k.spec (F of v.h), and with dlog its
// logarithm's derivative in alpha (the partials: dspec/dalpha = spec dlog).
DIFFSHADE_CLONES void CookTorrance(const Config& cfg, const float* front, const float* backm, Block& k, int m,
                                   float* dlog) {
  const bool ggx = cfg.specular == 4, vcavity = cfg.Flag(10);
  float* __restrict spec = k.spec;
  float* __restrict x = k.t0;  // Beckmann: the exponent, then its exp
  float* __restrict nh = k.t1;
  float* __restrict vh = k.t2;
  for (int q = 0; q < m; ++q) {  // the half vector's cosines (and Beckmann's exponent)
    const float hx = k.lx[q] + k.vx[q], hy = k.ly[q] + k.vy[q], hz = k.lz[q] + k.vz[q];
    const float sq = hx * hx + hy * hy + hz * hz;
    const float inv = sq > 0 ? 1.0f / std::sqrt(sq) : 0.0f;
    nh[q] = (k.nx[q] * hx + k.ny[q] * hy + k.nz[q] * hz) * inv;
    vh[q] = (k.vx[q] * hx + k.vy[q] * hy + k.vz[q] * hz) * inv;
  }
  if (!ggx) {
    const float a2f = front[14] * front[14], a2b = backm[14] * backm[14];
    for (int q = 0; q < m; ++q) {
      const float c2 = nh[q] * nh[q], c2s = c2 > kBeckmannFloor ? c2 : 1.0f;
      x[q] = -(1.0f - c2s) / (c2s * Pick(k.back[q], a2b, a2f));
    }
    ExpN(x, x, m);
  }
  for (int q = 0; q < m; ++q) {
    const float vdh = vh[q], ndh = nh[q], ndl = k.ndl[q], ndv = NdotV(k, q);
    const bool lit = ndl > 0 && ndv > 0;
    const float alpha = Pick(k.back[q], backm[14], front[14]), a2 = alpha * alpha;
    float D, dD;
    if (ggx) {
      const float c = std::max(ndh, 0.0f), c2 = std::min(c * c, 1.0f), d = (1.0f - c2) + c2 * a2;
      D = ndh > 0 ? a2 / (kPi * d * d) : 0.0f;
      dD = 2.0f / alpha - 4.0f * alpha * c2 / d;
    } else {
      const float c2 = ndh * ndh;
      const bool ok = c2 > kBeckmannFloor;
      const float c2s = ok ? c2 : 1.0f;
      D = ok ? x[q] / (kPi * a2 * c2s * c2s) : 0.0f;
      dD = 2.0f * (1.0f - c2s) / (c2s * a2 * alpha) - 2.0f / alpha;
    }
    const float cl = lit ? ndl : 1.0f, cv = lit ? ndv : 1.0f;
    float vis, dG = 0.0f;
    if (vcavity) {
      const float vh = vdh > 0 ? vdh : 1.0f;
      vis = std::min(1.0f / (4.0f * cl * cv), 0.5f * ndh / vh * std::min(1.0f / cl, 1.0f / cv));
    } else if (ggx) {
      vis = SmithGgx(cl, a2) * SmithGgx(cv, a2) / 4.0f;
      dG = SmithGgxDlog(cl, alpha) + SmithGgxDlog(cv, alpha);
    } else {
      float gl, gv;
      vis = SmithBeckmann(cl, alpha, &gl) * SmithBeckmann(cv, alpha, &gv) / 4.0f;
      dG = gl + gv;
    }
    float F = 1.0f;
    if (cfg.fresnel != 0) {
      const float ior = Pick(k.back[q], backm[13], front[13]);
      F = cfg.fresnel == 1 ? Schlick(Clip01(vdh), ior) : Dielectric(Clip01(vdh), ior);
    }
    spec[q] = lit ? D * vis * F * cl : 0.0f;
    if (dlog) dlog[q] = dD + dG;
  }
}

// Ward's tangent frame at the block's pixels: t (into tx, ty, tz) the material's tangent
// projected on the tangent plane (where it is along n, the world axis farthest from n), b = n x t.
inline void WardFrame(const Block& k, int q, const float* a, float* t, float* b) {
  const float nx = k.nx[q], ny = k.ny[q], nz = k.nz[q];
  const float na = nx * a[0] + ny * a[1] + nz * a[2];
  float px = a[0] - nx * na, py = a[1] - ny * na, pz = a[2] - nz * na;
  const float pp = px * px + py * py + pz * pz, aa = a[0] * a[0] + a[1] * a[1] + a[2] * a[2];
  if (!(pp > 1e-12f * std::max(aa, 1e-30f))) {
    const float ax = std::abs(nx), ay = std::abs(ny), az = std::abs(nz);
    const bool ex = ax <= ay && ax <= az, ey = !ex && ay <= az;
    const float e0 = ex ? 1.0f : 0.0f, e1 = ey ? 1.0f : 0.0f, e2 = (!ex && !ey) ? 1.0f : 0.0f;
    const float ne = nx * e0 + ny * e1 + nz * e2;
    px = e0 - nx * ne, py = e1 - ny * ne, pz = e2 - nz * ne;
  }
  const float sq = px * px + py * py + pz * pz;
  const float inv = sq > 0 ? 1.0f / std::sqrt(sq) : 0.0f;
  t[0] = px * inv, t[1] = py * inv, t[2] = pz * inv;
  b[0] = ny * t[2] - nz * t[1], b[1] = nz * t[0] - nx * t[2], b[2] = nx * t[1] - ny * t[0];
}

// Ward's anisotropic term into k.spec (times F of n.l with a Fresnel option); with dx, dy the
// derivatives of its logarithm in alpha_x and alpha_y.
DIFFSHADE_CLONES void Ward(const Config& cfg, const float* front, const float* backm, Block& k, int m, float* dx,
                           float* dy) {
  float* __restrict x = k.t0;
  float* __restrict spec = k.spec;
  for (int q = 0; q < m; ++q) {
    const bool bk = k.back[q] > 0;
    const float* mat = bk ? backm : front;
    float t[3], b[3];
    WardFrame(k, q, mat + 17, t, b);
    const float hx = k.lx[q] + k.vx[q], hy = k.ly[q] + k.vy[q], hz = k.lz[q] + k.vz[q];
    const float ndl = k.ndl[q], ndv = NdotV(k, q);
    const float hn0 = k.nx[q] * hx + k.ny[q] * hy + k.nz[q] * hz;
    const bool ok = ndl > 0 && ndv > 0 && hn0 > 0;
    const float hn = ok ? hn0 : 1.0f, ax = mat[14], ay = mat[15];
    const float ht = (hx * t[0] + hy * t[1] + hz * t[2]) / ax, hb = (hx * b[0] + hy * b[1] + hz * b[2]) / ay;
    const float e = (ht * ht + hb * hb) / (hn * hn);
    x[q] = -e;
    k.t1[q] = ok ? 1.0f : 0.0f;
    if (dx) dx[q] = 2.0f * ht * ht / (hn * hn * ax) - 1.0f / ax, dy[q] = 2.0f * hb * hb / (hn * hn * ay) - 1.0f / ay;
  }
  ExpN(x, x, m);
  for (int q = 0; q < m; ++q) {
    const bool bk = k.back[q] > 0;
    const float ax = bk ? backm[14] : front[14], ay = bk ? backm[15] : front[15];
    const bool ok = k.t1[q] > 0;
    const float cl = ok ? k.ndl[q] : 1.0f, cv = std::max(ok ? NdotV(k, q) : 1.0f, kWardGrazing);
    float w = ok ? x[q] * std::sqrt(cl / cv) / (4.0f * kPi * ax * ay) : 0.0f;
    if (cfg.fresnel != 0) {
      const float ior = bk ? backm[13] : front[13];
      w = (cfg.fresnel == 1 ? Schlick(k.ndl[q], ior) : Dielectric(k.ndl[q], ior)) * w;
    }
    spec[q] = w;
  }
}

// One light's direct terms (and per-light ambient) added to the block's m pixels. Not inlined:
// inlined into ShadeRange, the all-terms render at 512² took 19.8 ms against 9.4-10.9 ms.
__attribute__((noinline)) DIFFSHADE_CLONES void AddLight(const Config& cfg, const float* front, const float* backm, const float* li,
                                        Block& k, int m,
                                        bool derivatives = false) {
  const int kind = static_cast<int>(li[0]);
  float* __restrict lx = k.lx;
  float* __restrict ly = k.ly;
  float* __restrict lz = k.lz;
  float* __restrict att = k.att;
  if (kind == 0) {
    for (int q = 0; q < m; ++q) lx[q] = li[11], ly[q] = li[12], lz[q] = li[13], att[q] = 1.0f;
  } else {
    const float* a = li + 14;
    const float ox = li[11], oy = li[12], oz = li[13];
    for (int q = 0; q < m; ++q) {
      const float Lx = ox - k.px[q], Ly = oy - k.py[q], Lz = oz - k.pz[q];
      const float sq = Lx * Lx + Ly * Ly + Lz * Lz;
      const float d = std::sqrt(sq);
      const float inv = sq > 0 ? 1.0f / d : 0.0f;
      lx[q] = Lx * inv, ly[q] = Ly * inv, lz[q] = Lz * inv;
      att[q] = Radial(d, a);
    }
    if (kind == 2) {
      const float cos_cut = li[20], width = li[21] - cos_cut, e = li[22];
      const float ax = li[17], ay = li[18], az = li[19];
      float* __restrict cs = k.cs;
      float* __restrict lobe = k.lobe;
      for (int q = 0; q < m; ++q) cs[q] = -(lx[q] * ax + ly[q] * ay + lz[q] * az);
      SafePowN(cs, &e, 0, lobe, m);
      if (li[23] > 0) {  // a smooth edge: smoothstep from the cutoff to the inner cone
        const float safe = width > 0 ? width : 1.0f;
        for (int q = 0; q < m; ++q) {
          const float c = cs[q];
          const float t = width > 0 ? Clip01((c - cos_cut) / safe) : (c >= cos_cut ? 1.0f : 0.0f);
          att[q] = att[q] * (lobe[q] * t * t * (3.0f - 2.0f * t));
        }
      } else {
        for (int q = 0; q < m; ++q) att[q] = att[q] * (cs[q] >= cos_cut ? lobe[q] : 0.0f);
      }
    }
  }
  float* __restrict ndl = k.ndl;
  float* __restrict spec = k.spec;
  for (int q = 0; q < m; ++q) ndl[q] = k.nx[q] * lx[q] + k.ny[q] * ly[q] + k.nz[q] * lz[q];
  Diffuse(cfg, front, backm, k, m);
  if (cfg.specular == 1) {  // v.r = 2 (n.l)(n.v) - v.l
    for (int q = 0; q < m; ++q) {
      const float ndv = k.nx[q] * k.vx[q] + k.ny[q] * k.vy[q] + k.nz[q] * k.vz[q];
      const float vdl = k.vx[q] * lx[q] + k.vy[q] * ly[q] + k.vz[q] * lz[q];
      spec[q] = 2.0f * ndl[q] * ndv - vdl;
    }
  } else if (cfg.specular == 2) {  // n.h
    for (int q = 0; q < m; ++q) {
      const float hx = lx[q] + k.vx[q], hy = ly[q] + k.vy[q], hz = lz[q] + k.vz[q];
      const float sq = hx * hx + hy * hy + hz * hz;
      const float inv = sq > 0 ? 1.0f / std::sqrt(sq) : 0.0f;
      spec[q] = (k.nx[q] * hx + k.ny[q] * hy + k.nz[q] * hz) * inv;
    }
  }
  if (cfg.specular == 3 || cfg.specular == 4) {
    CookTorrance(cfg, front, backm, k, m, derivatives ? k.dl0 : nullptr);
  } else if (cfg.specular == 5) {
    Ward(cfg, front, backm, k, m, derivatives ? k.dl0 : nullptr, derivatives ? k.dl1 : nullptr);
  } else if (cfg.specular != 0) {
    const float* __restrict bk = k.back;
    const float* __restrict sh = k.sh;
    const float iorf = front[13], iorb = backm[13];
    SafePowN(spec, sh, 1, spec, m);
    for (int q = 0; q < m; ++q) spec[q] = ndl[q] > 0 ? spec[q] : 0.0f;
    if (cfg.fresnel == 1) {
      for (int q = 0; q < m; ++q) spec[q] = Schlick(ndl[q], Pick(bk[q], iorb, iorf)) * spec[q];
    } else if (cfg.fresnel == 2) {
      for (int q = 0; q < m; ++q) spec[q] = Dielectric(ndl[q], Pick(bk[q], iorb, iorf)) * spec[q];
    }
  } else {
    for (int q = 0; q < m; ++q) spec[q] = 0.0f;
  }
  // (flags as factors of 1 or 0 and separate loops: branch-free inner loops, vectorised; the
  // diffuse switch is in k.dif)
  const bool has_spec = li[10] > 0;
  for (int c = 0; c < 3; ++c) {
    const float color = li[1 + c], sc = li[7 + c];
    const float* __restrict kd = k.kd[c];
    const float* __restrict ks = k.ks[c];
    float* __restrict out = k.col[c];
    // the order of _lighting._terms: one colour, or the specular with its own
    if (has_spec) {
      for (int q = 0; q < m; ++q) {
        const float acc = kd[q] * k.dif[q];
        out[q] += att[q] * (acc * color) + att[q] * ((ks[q] * spec[q]) * sc);
      }
    } else {
      for (int q = 0; q < m; ++q) {
        const float acc = kd[q] * k.dif[q];
        out[q] += att[q] * ((acc + ks[q] * spec[q]) * color);
      }
    }
    if (cfg.Flag(3)) {  // per-light ambient
      const float amb = li[4 + c];
      const float* __restrict ka = k.ka[c];
      float* __restrict base = k.base[c];
      for (int q = 0; q < m; ++q) base[q] += att[q] * (ka[q] * amb);
    }
  }
}

// A face's texture coordinates (_texture: perspective-correct, u = sum b_i u_i with the
// barycentrics b_i = E_i / sum E of its planes c) and, for trilinear maps, what their derivatives
// per pixel step need (_texture.pixel_derivatives: with the planes' x and y slopes a_i, b_i,
// du/dx = (sum a_i u_i - u sum a_i) w / det, and w / det = 1 / sum E); Gouraud: its corners'
// colours of each mapped part on the side lit (interpolated as the coordinates). Taken per face,
// once a render (Of, in Prepare's threads), and read by each of the face's runs of pixels: taken
// per run, with the prefetches of the next run's corners, it was about a quarter of ShadeRange's
// time in a 512² Gouraud render with a map. The record: U (3), V (3), axu, axv, ayu, ayv, sx, sy,
// then per part its corners' colours (3 x 3).
constexpr int kFaceMapHead = 12;
struct FaceMap {
  const float* r;
  const float* U() const { return r; }
  const float* V() const { return r + 3; }
  const float* Slopes() const { return r + 6; }  // axu, axv, ayu, ayv, sx, sy
  // The record of face t (faces: its kFace floats) into r.
  static void Of(const Maps& mp, const float* uv, const int32_t* tri, const float* parts, int64_t num_verts,
                 bool two_sided, int64_t t, const float* c, float* r) {
    int64_t vid[3];
    float U[3], V[3];
    for (int j = 0; j < 3; ++j) {
      vid[j] = std::min<int64_t>(std::max<int32_t>(tri[3 * t + j], 0), num_verts - 1);
      U[j] = uv[2 * vid[j]], V[j] = uv[2 * vid[j] + 1];
      r[j] = U[j], r[3 + j] = V[j];
    }
    float axu = (c[1] * U[0] + c[4] * U[1]) + c[7] * U[2], axv = (c[1] * V[0] + c[4] * V[1]) + c[7] * V[2];
    float ayu = (c[2] * U[0] + c[5] * U[1]) + c[8] * U[2], ayv = (c[2] * V[0] + c[5] * V[1]) + c[8] * V[2];
    r[10] = ((c[1] + c[4]) + c[7]) * mp.sx, r[11] = ((c[2] + c[5]) + c[8]) * mp.sy;  // (and NDC per pixel step)
    r[6] = axu * mp.sx, r[7] = axv * mp.sx, r[8] = ayu * mp.sy, r[9] = ayv * mp.sy;
    const bool back = two_sided && !(c[31] > 0);  // (PointsOf's side)
    for (int g = 0; g < mp.parts; ++g) {
      const float* at = parts + (2 * g + (back ? 1 : 0)) * num_verts * 3;
      for (int j = 0; j < 3; ++j) {
        for (int ch = 0; ch < 3; ++ch) r[kFaceMapHead + 9 * g + 3 * j + ch] = at[3 * vid[j] + ch];
      }
    }
  }
  // The mapped parts' colours at a run of n pixels (the block's entry m on: its barycentrics),
  // eight at a time (PointsOf).
  inline void Parts(const Maps& mp, Block& k, int m, int n) const;
};

// Phong: the material at the block's pixels, the lit side's constants (the back material on the
// back side), each mapped field times its map (maps come with one material: no back material).
// Lit one-sided, a field without a map is the front's constant at every pixel of every block:
// written once, at the first block (k.fixed), for all kBlock entries.
__attribute__((always_inline)) inline void PixelMaterial(const Config& cfg, const Maps& mp, const float* front, const float* backm, Block& k, int m) {
  const float* __restrict bk = k.back;
  const bool one_sided = !cfg.Flag(4), fill = one_sided && !k.fixed;  // (the constants, this once)
  float(*fields[4])[kBlock] = {k.ke, k.ka, k.kd, k.ks};
  const bool used[5] = {cfg.Flag(0), cfg.Flag(1) || cfg.Flag(3), cfg.Flag(2), cfg.specular != 0, cfg.specular != 0};
  for (int f = 0; f < 4; ++f) {
    if (!used[f]) continue;  // (zero from ShadeRange's start: a term that is off multiplies it by 0)
    for (int c = 0; c < 3; ++c) {
      float* __restrict dst = fields[f][c];
      const bool one = f == 3 && cfg.fresnel != 0;  // the Fresnel term is the specular weight
      const float kf = one ? 1.0f : front[3 * f + c], kb = one ? 1.0f : backm[3 * f + c];
      if (mp.field[f] >= 0 && !one) {
        const float* __restrict t = k.tex[mp.field[f]][c];
        for (int q = 0; q < m; ++q) dst[q] = kf * t[q];
      } else if (!one_sided) {
        for (int q = 0; q < m; ++q) dst[q] = Pick(bk[q], kb, kf);
      } else if (fill) {
        for (int q = 0; q < kBlock; ++q) dst[q] = kf;
      }
    }
  }
  const float shf = front[12], shb = backm[12];
  if (used[4] && mp.field[4] >= 0) {
    const float* __restrict t = k.tex[mp.field[4]][0];
    for (int q = 0; q < m; ++q) k.sh[q] = shf * t[q];
  } else if (used[4] && !one_sided) {
    for (int q = 0; q < m; ++q) k.sh[q] = Pick(bk[q], shb, shf);
  } else if (used[4] && fill) {
    for (int q = 0; q < kBlock; ++q) k.sh[q] = shf;
  }
  k.fixed = true;
}

// Eight floats (GCC's and Clang's vector extensions: one AVX2 register in the AVX2 clone, two SSE
// ones otherwise), for loops over a face's run of pixels: at 512² a run is 6.4 pixels on average,
// shorter than a vectorised loop's minimum, so such a loop ran as its scalar remainder. A run is
// done in vectors of eight whatever its length; the lanes past its end are written into the
// block's room (kRoom) and overwritten by the next run, or never read.
typedef float V8 __attribute__((vector_size(32)));
typedef int32_t I8 __attribute__((vector_size(32)));
typedef int64_t L8 __attribute__((vector_size(64)));
template <class T>
inline T Load8(const void* p) {
  T v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
template <class T>
inline void Store8(void* p, T v) {
  std::memcpy(p, &v, sizeof(v));
}
// Eight floats from p, of which only the first `avail` may be read (the rest: 0).
inline V8 Load8Upto(const float* p, int64_t avail) {
  if (avail >= 8) return Load8<V8>(p);
  float r[8] = {};
  std::memcpy(r, p, static_cast<size_t>(avail) * sizeof(float));
  return Load8<V8>(r);
}

__attribute__((always_inline)) inline void FaceMap::Parts(const Maps& mp, Block& k, int m, int n) const {
  for (int g = 0; g < mp.parts; ++g) {
    const float* at = r + kFaceMapHead + 9 * g;
    for (int i = 0; i < n; i += 8) {
      const int q = m + i;
      const V8 b0 = Load8<V8>(k.b0 + q), b1 = Load8<V8>(k.b1 + q), b2 = Load8<V8>(k.b2 + q);
      for (int ch = 0; ch < 3; ++ch) {
        const float p0 = at[ch], p1 = at[3 + ch], p2 = at[6 + ch];
        Store8(k.part[g][ch] + q, (p0 * b0 + p1 * b1) + p2 * b2);
      }
    }
  }
}

// The pixels b + i (0 < i < len <= 64) that see another face than the pixel before them, as bits
// i of a word (bit 0 set): where a block's runs of one face start. Eight (AVX2) or four (SSE2)
// ids compared at once; one at a time, the scan for a run's end (a compare and a branch a pixel)
// took a tenth of the shading kernel's time.
// (bits i to len - 1 added to bits one pixel at a time: the vector loops' tail, and all of it
// off x86-64)
inline uint64_t FaceChangesFrom(const int32_t* ids, int64_t b, int i, int len, uint64_t bits) {
  for (; i < len; ++i) bits |= static_cast<uint64_t>(ids[b + i] != ids[b + i - 1]) << i;
  return bits;
}
#if DIFFSHADE_HAS_CLONES
__attribute__((target("avx2"))) uint64_t FaceChanges(const int32_t* ids, int64_t b, int len) {
  uint64_t bits = 1;
  int i = 1;
  for (; i + 8 <= len; i += 8) {
    const __m256i a = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(ids + b + i));
    const __m256i before = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(ids + b + i - 1));
    const unsigned same = static_cast<unsigned>(_mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(a, before))));
    bits |= static_cast<uint64_t>(~same & 0xffu) << i;
  }
  return FaceChangesFrom(ids, b, i, len, bits);
}
__attribute__((target("default"))) uint64_t FaceChanges(const int32_t* ids, int64_t b, int len) {
  uint64_t bits = 1;
  int i = 1;
  for (; i + 4 <= len; i += 4) {
    const __m128i a = _mm_loadu_si128(reinterpret_cast<const __m128i*>(ids + b + i));
    const __m128i before = _mm_loadu_si128(reinterpret_cast<const __m128i*>(ids + b + i - 1));
    const unsigned same = static_cast<unsigned>(_mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(a, before))));
    bits |= static_cast<uint64_t>(~same & 0xfu) << i;
  }
  return FaceChangesFrom(ids, b, i, len, bits);
}
#else
uint64_t FaceChanges(const int32_t* ids, int64_t b, int len) { return FaceChangesFrom(ids, b, 1, len, 1); }
#endif

// The covered pixels' points of the block of pixels [b0, b1) (col, row: the first one's, in a
// grid; advanced), each run of empty ones handed to empty(first, end): the barycentrics
// b_i = E_i / sum_k E_k of their face's edge functions, the corners' normals and positions
// interpolated with them (a plane per attribute, sum_i E_i a_i, would save work but lose
// accuracy: up to 2e-5 off the JAX stages, which this form holds to 6e-6). A row's pixels come
// in runs that see one face, each done in vectors of eight with the face's numbers held. With
// maps (uvs), each pixel's texture coordinates too (FaceMap), and for trilinear maps
// (derivatives) their derivatives per pixel step.
template <bool uvs, bool derivatives, class Empty>
__attribute__((always_inline)) inline int PointsOf(const Pixels& px, const float* faces, bool two_sided,
                                                   bool gouraud, const Maps& mp, int64_t b0, int64_t b1,
                                                   int64_t& col, int64_t& row, Block& k, Empty empty) {
  const int32_t* ids = px.ids;
  const int64_t width = px.width;
  const bool grid = px.grid;
  static_assert(kBlock <= 64, "a block's runs are bits of a word");
  const int len = static_cast<int>(b1 - b0);
  uint64_t starts = FaceChanges(ids, b0, len);
  if (grid) {  // (a run stays in its row)
    for (int64_t i = (width - col) % width; i < len; i += width) starts |= uint64_t{1} << i;
  }
  int m = 0;
  while (starts != 0) {
    const int i0 = __builtin_ctzll(starts);
    starts &= starts - 1;
    const int i1 = starts != 0 ? __builtin_ctzll(starts) : len;
    const int64_t p = b0 + i0, r = b0 + i1;
    const int32_t t = ids[p];
    if (r < px.n) {  // the next run's face record (three cache lines), fetched while this run is done
      const int64_t tn = std::max(ids[r], 0);
      const char* next = reinterpret_cast<const char*>(faces + tn * kFace);
      __builtin_prefetch(next), __builtin_prefetch(next + 64), __builtin_prefetch(next + 128);
      if (uvs) {  // and its FaceMap record
        const char* rec = reinterpret_cast<const char*>(mp.faces + tn * mp.face_floats);
        for (int b = 0; b < mp.face_floats * 4; b += 64) __builtin_prefetch(rec + b);
        __builtin_prefetch(rec + mp.face_floats * 4 - 1);
      }
    }
    const int n = i1 - i0;
    if (t < 0) {
      empty(p, r);
    } else {
      const float* __restrict c = faces + static_cast<int64_t>(t) * kFace;
      const float back = (two_sided && !(c[31] > 0)) ? 1.0f : 0.0f;
      const int o = (gouraud && back > 0) ? 32 : 13;  // Gouraud: the back colours on a back face
      const int64_t at = grid ? col : p;  // the run's first pixel centre in xs (and ys, not a grid)
      const int64_t avail = (grid ? width : px.n) - at;  // (centres there)
      const float* __restrict xr = px.xs + at;
      const float* __restrict yr = px.ys + (grid ? row : p);
      const FaceMap fm{uvs ? mp.faces + static_cast<int64_t>(t) * mp.face_floats : nullptr};
      for (int i = 0; i < n; i += 8) {
        const int q = m + i;
        const V8 x = Load8Upto(xr + i, avail - i);
        const V8 y = grid ? V8{} + yr[0] : Load8Upto(yr + i, avail - i);
        const V8 e0 = c[0] + x * c[1] + y * c[2], e1 = c[3] + x * c[4] + y * c[5];
        const V8 e2 = c[6] + x * c[7] + y * c[8];
        const V8 s = e0 + e1 + e2;
        const I8 ok = s != 0;
        const V8 inv = ok ? 1.0f / s : V8{} + 1.0f;
        const V8 b0 = ok ? e0 * inv : V8{}, b1 = ok ? e1 * inv : V8{}, b2 = ok ? e2 * inv : V8{};
        Store8(k.nx + q, (c[o] * b0 + c[o + 3] * b1) + c[o + 6] * b2);
        Store8(k.ny + q, (c[o + 1] * b0 + c[o + 4] * b1) + c[o + 7] * b2);
        Store8(k.nz + q, (c[o + 2] * b0 + c[o + 5] * b1) + c[o + 8] * b2);
        Store8(k.px + q, (c[22] * b0 + c[25] * b1) + c[28] * b2);
        Store8(k.py + q, (c[23] * b0 + c[26] * b1) + c[29] * b2);
        Store8(k.pz + q, (c[24] * b0 + c[27] * b1) + c[30] * b2);
        // (D / sum E in exact arithmetic; as the corners' mean it keeps its precision at a face
        // seen edge-on, where both are small differences of large terms: _raster.fragments)
        const V8 wi = (c[9] * b0 + c[10] * b1) + c[11] * b2;
        Store8(k.w + q, wi);
        Store8(k.back + q, V8{} + back);
        Store8(k.b0 + q, b0), Store8(k.b1 + q, b1), Store8(k.b2 + q, b2);
        Store8(k.pix + q, (p + i) + L8{0, 1, 2, 3, 4, 5, 6, 7});
        Store8(k.face + q, I8{} + t);
        if (uvs) {
          const float* U = fm.U();
          const float* V = fm.V();
          const V8 ui = (U[0] * b0 + U[1] * b1) + U[2] * b2;
          const V8 vi = (V[0] * b0 + V[1] * b1) + V[2] * b2;
          Store8(k.u + q, ui), Store8(k.v + q, vi);
          if (derivatives) {  // (1 / sum E; 0 on an empty face)
            const V8 scale = c[12] != 0 ? (ok ? wi / c[12] : V8{}) : V8{};
            const float* a = fm.Slopes();
            Store8(k.dux + q, (a[0] - ui * a[4]) * scale), Store8(k.dvx + q, (a[1] - vi * a[4]) * scale);
            Store8(k.duy + q, (a[2] - ui * a[5]) * scale), Store8(k.dvy + q, (a[3] - vi * a[5]) * scale);
          }
        }
      }
      if (uvs && mp.parts > 0) fm.Parts(mp, k, m, n);
      m += n;
    }
    if (grid) {
      col += n;
      if (col == width) col = 0, ++row;
    }
  }
  return m;
}

template <class Empty>
__attribute__((always_inline)) inline int Points(const Pixels& px, const float* faces, bool two_sided, bool gouraud,
                                                 const Maps& mp, int64_t b0, int64_t b1, int64_t& col, int64_t& row,
                                                 Block& k, Empty empty) {
  if (!mp.any()) return PointsOf<false, false>(px, faces, two_sided, gouraud, mp, b0, b1, col, row, k, empty);
  if (!mp.derivatives) return PointsOf<true, false>(px, faces, two_sided, gouraud, mp, b0, b1, col, row, k, empty);
  return PointsOf<true, true>(px, faces, two_sided, gouraud, mp, b0, b1, col, row, k, empty);
}

// The unit normal at the block's m points (reversed where the back side is lit) and the unit
// vector to the viewer.
__attribute__((always_inline)) inline void Surface(bool infinite, const float* eye, const float* view_z, Block& k,
                                                   int m) {
  float* __restrict nx = k.nx;
  float* __restrict ny = k.ny;
  float* __restrict nz = k.nz;
  const float* __restrict bk = k.back;
  for (int q = 0; q < m; ++q) {  // the unit normal, reversed where the back side is lit
    const float sq = nx[q] * nx[q] + ny[q] * ny[q] + nz[q] * nz[q];
    const float r = sq > 0 ? 1.0f / std::sqrt(sq) : 0.0f;
    const float inv = r * (1.0f - 2.0f * bk[q]);
    nx[q] *= inv, ny[q] *= inv, nz[q] *= inv;
  }
  float* __restrict vx = k.vx;
  float* __restrict vy = k.vy;
  float* __restrict vz = k.vz;
  if (infinite) {
    for (int q = 0; q < m; ++q) vx[q] = view_z[0], vy[q] = view_z[1], vz[q] = view_z[2];
  } else {
    for (int q = 0; q < m; ++q) {
      const float dx = eye[0] - k.px[q], dy = eye[1] - k.py[q], dz = eye[2] - k.pz[q];
      const float sq = dx * dx + dy * dy + dz * dz;
      const float inv = sq > 0 ? 1.0f / std::sqrt(sq) : 0.0f;
      vx[q] = dx * inv, vy[q] = dy * inv, vz[q] = dz * inv;
    }
  }
}

// The fog's factor at the block's m pixels (ShadeRange's and the partials'): the distance (the
// eye-space depth, or to the eye) into dist, then the factor into f (f may be dist).
inline void FogFactor(int mode, bool depth, const float* fog, const float* eye, const Block& k, int m,
                      float* dist, float* f) {
  for (int q = 0; q < m; ++q) {
    const float dx = k.px[q] - eye[0], dy = k.py[q] - eye[1], dz = k.pz[q] - eye[2];
    dist[q] = depth ? k.w[q] : std::sqrt(dx * dx + dy * dy + dz * dz);
  }
  if (mode == 1) {
    const float den = fog[4] - fog[3];
    for (int q = 0; q < m; ++q) {
      const float d = dist[q];
      f[q] = den > 0 ? Clip01((fog[4] - d) / den) : (d <= fog[4] ? 1.0f : 0.0f);
    }
  } else {
    for (int q = 0; q < m; ++q) {
      const float r = fog[5] * dist[q];
      f[q] = mode == 2 ? -r : -(r * r);
    }
    ExpN(f, f, m);
  }
}

// The block's m colours (col) into out [N, 3] at their pixels: one interleaving loop over
// contiguous memory where the block's covered pixels are one stretch (most blocks inside an
// object), else pixel by pixel.
inline void Write(const Block& k, int m, float* out) {
  if (m > 0 && k.pix[m - 1] - k.pix[0] == m - 1) {
    float* __restrict o = out + 3 * k.pix[0];
    const float* __restrict r = k.col[0];
    const float* __restrict g = k.col[1];
    const float* __restrict b = k.col[2];
    for (int q = 0; q < m; ++q) o[3 * q] = r[q], o[3 * q + 1] = g[q], o[3 * q + 2] = b[q];
    return;
  }
  for (int q = 0; q < m; ++q) {
    float* o = out + 3 * k.pix[q];
    o[0] = k.col[0][q], o[1] = k.col[1][q], o[2] = k.col[2][q];
  }
}

DIFFSHADE_CLONES void ShadeRange(const Config& cfg, const Pixels& px, const float* faces, const float* params,
                                  const float* lights, int64_t num_lights, const Maps& mp, int64_t p0, int64_t p1,
                                  float* out) {
  const float* front = params;
  const float* backm = params + kMat;
  const float* amb_light = params + 2 * kMat;
  const float* eye = amb_light + 3;
  const float* view_z = eye + 3;
  const float* fog = view_z + 3;  // colour (3), start, end, density
  const float* background = fog + 6;
  const float* gain = background + 3;
  const bool two_sided = cfg.Flag(4), infinite = cfg.Flag(5), clamp = cfg.Flag(6), clamp_after = cfg.Flag(7);
  const bool gouraud = cfg.Flag(8);
  const bool emission = cfg.Flag(0), ambient = cfg.Flag(1);
  const int fog_mode = cfg.fog & 3;
  const bool fog_depth = (cfg.fog & 4) != 0;
  Block k;
  // the fields of the terms that are off stay 0 (PixelMaterial does not write them)
  std::memset(k.ke, 0, sizeof(k.ke)), std::memset(k.ka, 0, sizeof(k.ka)), std::memset(k.kd, 0, sizeof(k.kd));
  std::memset(k.ks, 0, sizeof(k.ks)), std::memset(k.sh, 0, sizeof(k.sh));
  int64_t col = px.grid ? p0 % px.width : 0, row = px.grid ? p0 / px.width : 0;  // (no division per pixel)
  for (int64_t b0 = p0; b0 < p1; b0 += kBlock) {
    const int64_t b1 = std::min(b0 + kBlock, p1);
    const int m =
        Points(px, faces, two_sided, gouraud, mp, b0, b1, col, row, k, [&](int64_t p, int64_t r) {
          for (int64_t q = p; q < r; ++q) {
            for (int c = 0; c < 3; ++c) out[3 * q + c] = background[c] * gain[c];
          }
        });
    for (int i = 0; i < mp.count; ++i) SampleMap(mp.map[i], k, m, k.tex[i]);
    if (gouraud) {  // the interpolated colour is the pixel's (lit, and clamped if asked, at the vertices)
      for (int q = 0; q < m; ++q) k.col[0][q] = k.nx[q], k.col[1][q] = k.ny[q], k.col[2][q] = k.nz[q];
      for (int g = 0; g < mp.parts; ++g) {  // each mapped part times its map (_lighting._modulated_side)
        for (int c = 0; c < 3; ++c) {
          const float* __restrict t = k.tex[mp.part_map[g]][c];
          const float* __restrict part = k.part[g][c];
          float* __restrict colc = k.col[c];
          for (int q = 0; q < m; ++q) colc[q] = colc[q] + t[q] * part[q];
        }
      }
    } else {
      PixelMaterial(cfg, mp, front, backm, k, m);
      Surface(infinite, eye, view_z, k, m);
      for (int c = 0; c < 3; ++c) {
        for (int q = 0; q < m; ++q) k.col[c][q] = 0.0f, k.base[c][q] = 0.0f;
      }
      for (int64_t i = 0; i < num_lights; ++i) AddLight(cfg, front, backm, lights + i * kLight, k, m);
    }
    if (fog_mode != 0) FogFactor(fog_mode, fog_depth, fog, eye, k, m, k.fog, k.fog);
    const float amb_on = ambient ? 1.0f : 0.0f, em_on = emission ? 1.0f : 0.0f;
    for (int c = 0; c < 3; ++c) {
      const float ia = amb_light[c];
      float* __restrict colc = k.col[c];
      const float* __restrict base = k.base[c];
      const float* __restrict ka = k.ka[c];
      const float* __restrict ke = k.ke[c];
      if (!gouraud) {
        for (int q = 0; q < m; ++q) {  // base + direct (the ambient and emission terms where on)
          const float b = (base[q] + (ka[q] * ia) * amb_on) + ke[q] * em_on;
          colc[q] = b + colc[q];
        }
      }
      if (clamp) {
        for (int q = 0; q < m; ++q) colc[q] = Clip01(colc[q]);
      }
      if (fog_mode != 0) {
        const float fc = fog[c];
        const float* __restrict f = k.fog;
        for (int q = 0; q < m; ++q) colc[q] = f[q] * colc[q] + (1.0f - f[q]) * fc;
      }
      if (clamp_after) {  // OpenGL: the vertex colours were clamped, and the fogged colour is
        for (int q = 0; q < m; ++q) colc[q] = Clip01(colc[q]);
      }
      const float gc = gain[c];
      for (int q = 0; q < m; ++q) colc[q] = colc[q] * gc;
    }
    Write(k, m, out);
  }
}

// ---------------------------------------------------------------------------------------------
// Forward-mode partials (diffshade/_fast.py: the kernel's jvp rule): the derivatives of the
// render along K directions of the scene's numbers and lights (dirs [K, kParams + L kLight]),
// for the numbers the render is linear or nearly so in: the materials' colours and shininess,
// the lights' colours, ambient colours and attenuation, the ambient light, the fog, background
// and gain (Supported; the others are the stages'). Phong: the render's own quantities per light
// (its attenuation, n.l, specular term: AddLight's) are computed as for the value, and each
// direction's derivative is accumulated from them in closed form, one loop over the block's
// pixels per nonzero (number, direction) pair. Gouraud: the vertices' colours' tangents
// (corners, from JAX) interpolated. Then both through the clamp, fog and gain.

struct Entry {
  int slot, j;  // the number (index into params, then lights) and the direction
  float w;      // dirs[j][slot]
};

// Whether the partials kernel differentiates by params[slot] (slot < kParams) or by a light's
// number (slot - kParams modulo kLight).
inline bool Supported(int64_t slot) {
  if (slot < kParams) {
    const int64_t s = slot < 2 * kMat ? slot % kMat : slot;
    // (not ior, the tangent, the eye, the view axis)
    return slot < 2 * kMat ? (s <= 12 || (s >= 14 && s <= 16)) : (s < 2 * kMat + 3 || s >= 2 * kMat + 9);
  }
  const int64_t f = (slot - kParams) % kLight;
  return (f >= 1 && f <= 9) || (f >= 14 && f <= 16);
}

// dcol[j][c] += w g (the block's m pixels).
inline void Accumulate(float* __restrict dst, float w, const float* __restrict g, int m) {
  for (int q = 0; q < m; ++q) dst[q] += w * g[q];
}

// The weight per pixel of a material number (front: the front side's pixels, or every pixel
// times the map where the field has one; back: the back side's).
inline void Side(const Maps& mp, const Block& k, int field, int channel, bool back_slot, int m, float* __restrict sel) {
  const float* __restrict bk = k.back;
  if (mp.field[field] >= 0) {
    const float* __restrict t = k.tex[mp.field[field]][field == 4 ? 0 : channel];
    for (int q = 0; q < m; ++q) sel[q] = back_slot ? 0.0f : t[q];
  } else {
    for (int q = 0; q < m; ++q) sel[q] = back_slot ? bk[q] : 1.0f - bk[q];
  }
}

// dcol[e.j][c] += w g k_s I_s (the specular colour's light: its own, or its colour) for a
// specular factor's derivative g (times the attenuation and the side) at the block's pixels.
inline void SpecularPartial(const float* li, bool has_spec, const Entry& e, const float* __restrict g, const Block& k,
                            int m, float* dcol) {
  for (int c = 0; c < 3; ++c) {
    const float lc = has_spec ? li[7 + c] : li[1 + c];
    float* __restrict d = dcol + (int64_t{e.j} * 3 + c) * kBlock;
    const float* __restrict ks = k.ks[c];
    for (int q = 0; q < m; ++q) d[q] += e.w * (g[q] * ks[q] * lc);
  }
}

// One light's part of every direction's derivative of the (unclamped, unfogged) colour, after
// AddLight filled the block's att, ndl, spec (and l) for it.
DIFFSHADE_CLONES void LightPartials(const Config& cfg, const Maps& mp, const float* front, const float* backm,
                                    const float* li, int64_t light, const std::vector<Entry>& es, int64_t m_pixels,
                                    Block& k, float* dcol, float* g, float* h) {
  const int m = static_cast<int>(m_pixels);
  const int kind = static_cast<int>(li[0]);
  const bool has_spec = li[10] > 0, per_light_ambient = cfg.Flag(3);
  const float dif_on = cfg.Flag(2) ? 1.0f : 0.0f;
  const int64_t first = kParams + light * kLight;
  float* __restrict sel = h;
  float* __restrict gg = g;
  for (const Entry& e : es) {
    const bool mat = e.slot < 2 * kMat;
    if (!mat && (e.slot < first || e.slot >= first + kLight)) continue;
    const int f = mat ? static_cast<int>(e.slot % kMat) : static_cast<int>(e.slot - first);
    if (mat && f >= 14 && f <= 16) {  // the other local models' roughness, roughness_y, sigma
      const bool back_slot = e.slot >= kMat;
      for (int q = 0; q < m; ++q) sel[q] = back_slot ? k.back[q] : 1.0f - k.back[q];
      if (f == 16) {  // Oren-Nayar's sigma: d dif / d sigma = (n.l) (dA + dB across), times k_d I_p att
        if (!cfg.Flag(9) || dif_on == 0.0f) continue;
        float a, b, da, db;
        OrenNayarAB(back_slot ? backm[16] : front[16], &a, &b, &da, &db);
        for (int q = 0; q < m; ++q) {
          const float ndl = k.ndl[q], ndv = NdotV(k, q);
          const float ldv = k.lx[q] * k.vx[q] + k.ly[q] * k.vy[q] + k.lz[q] * k.vz[q];
          const float across = OrenNayarAcross(ndl, ndv, ldv);
          gg[q] = ndl > 0 && std::max(ndl, ndv) > 0 ? k.att[q] * ndl * (da + db * across) * sel[q] : 0.0f;
        }
        for (int c = 0; c < 3; ++c) {
          float* __restrict d = dcol + (int64_t{e.j} * 3 + c) * kBlock;
          const float* __restrict kd = k.kd[c];
          const float lc = li[1 + c];
          for (int q = 0; q < m; ++q) d[q] += e.w * (gg[q] * kd[q] * lc);
        }
        continue;
      }
      // d spec / d alpha = spec dlog (AddLight's, with the derivatives: dl0 in alpha, Ward's dl1 in alpha_y)
      if (!((cfg.specular == 3 || cfg.specular == 4) && f == 14) && cfg.specular != 5) continue;
      const float* __restrict dl = f == 14 ? k.dl0 : k.dl1;
      for (int q = 0; q < m; ++q) gg[q] = k.spec[q] != 0.0f ? k.att[q] * k.spec[q] * dl[q] * sel[q] : 0.0f;
      SpecularPartial(li, has_spec, e, gg, k, m, dcol);
      continue;
    }
    if (mat && f == 12) {  // shininess: d spec / d m = spec log(the specular base) where spec is on
      if (cfg.specular == 0 || cfg.specular > 2) continue;
      Side(mp, k, 4, 0, e.slot >= kMat, m, sel);
      if (cfg.specular == 1) {  // the specular base, as AddLight's
        for (int q = 0; q < m; ++q) {
          const float ndv = k.nx[q] * k.vx[q] + k.ny[q] * k.vy[q] + k.nz[q] * k.vz[q];
          const float vdl = k.vx[q] * k.lx[q] + k.vy[q] * k.ly[q] + k.vz[q] * k.lz[q];
          gg[q] = 2.0f * k.ndl[q] * ndv - vdl;
        }
      } else {
        for (int q = 0; q < m; ++q) {
          const float hx = k.lx[q] + k.vx[q], hy = k.ly[q] + k.vy[q], hz = k.lz[q] + k.vz[q];
          const float sq = hx * hx + hy * hy + hz * hz;
          const float inv = sq > 0 ? 1.0f / std::sqrt(sq) : 0.0f;
          gg[q] = (k.nx[q] * hx + k.ny[q] * hy + k.nz[q] * hz) * inv;
        }
      }
      for (int q = 0; q < m; ++q) gg[q] = k.spec[q] != 0.0f ? gg[q] : 1.0f;
      LogN(gg, gg, m);
      for (int q = 0; q < m; ++q) gg[q] = k.spec[q] != 0.0f ? k.att[q] * k.spec[q] * gg[q] * sel[q] : 0.0f;
      SpecularPartial(li, has_spec, e, gg, k, m, dcol);
      continue;
    }
    if (mat) {  // a colour of the material: the term it weighs, on its side
      const int field = f / 3, c = f % 3;
      if (field == 0 || (field == 3 && cfg.fresnel != 0)) continue;  // (emission: ShadePartials; F replaces k_s)
      if (field == 1 && !per_light_ambient) continue;
      Side(mp, k, field, c, e.slot >= kMat, m, sel);
      const float lc = field == 1 ? li[4 + c] : (field == 3 && has_spec) ? li[7 + c] : li[1 + c];
      float* __restrict d = dcol + (int64_t{e.j} * 3 + c) * kBlock;
      if (field == 1) {
        for (int q = 0; q < m; ++q) d[q] += e.w * (k.att[q] * lc * sel[q]);
      } else if (field == 2) {
        for (int q = 0; q < m; ++q) d[q] += e.w * (k.att[q] * k.dif[q] * lc * sel[q]);
      } else {
        for (int q = 0; q < m; ++q) d[q] += e.w * (k.att[q] * k.spec[q] * lc * sel[q]);
      }
      continue;
    }
    if (f >= 1 && f <= 9) {  // the light's colour, ambient colour or specular colour
      const int c = (f - 1) % 3, which = (f - 1) / 3;
      float* __restrict d = dcol + (int64_t{e.j} * 3 + c) * kBlock;
      const float* __restrict kd = k.kd[c];
      const float* __restrict ks = k.ks[c];
      const float* __restrict ka = k.ka[c];
      if (which == 0) {  // colour
        for (int q = 0; q < m; ++q) {
          const float dif = kd[q] * k.dif[q];
          d[q] += e.w * (k.att[q] * (has_spec ? dif : dif + ks[q] * k.spec[q]));
        }
      } else if (which == 1 && per_light_ambient) {
        for (int q = 0; q < m; ++q) d[q] += e.w * (k.att[q] * ka[q]);
      } else if (which == 2 && has_spec) {
        for (int q = 0; q < m; ++q) d[q] += e.w * (k.att[q] * (ks[q] * k.spec[q]));
      }
      continue;
    }
    if (kind == 0) continue;  // attenuation (a directional light has none)
    const int i = f - 14;
    const float* a = li + 14;
    for (int q = 0; q < m; ++q) {  // d att / d a_i = -att d^i / (a0 + a1 d + a2 d^2) where it is not floored
      const float dx = li[11] - k.px[q], dy = li[12] - k.py[q], dz = li[13] - k.pz[q];
      const float dist = std::sqrt(dx * dx + dy * dy + dz * dz);
      const float den = a[0] + a[1] * dist + a[2] * dist * dist;
      const float pw = i == 0 ? 1.0f : (i == 1 ? dist : dist * dist);
      gg[q] = den > 2.2737368e-13f ? -k.att[q] * pw / den : 0.0f;
    }
    for (int c = 0; c < 3; ++c) {  // times the light's unattenuated terms
      float* __restrict d = dcol + (int64_t{e.j} * 3 + c) * kBlock;
      const float* __restrict kd = k.kd[c];
      const float* __restrict ks = k.ks[c];
      const float* __restrict ka = k.ka[c];
      const float color = li[1 + c], sc = has_spec ? li[7 + c] : li[1 + c], amb = per_light_ambient ? li[4 + c] : 0.0f;
      for (int q = 0; q < m; ++q) {
        const float u = kd[q] * k.dif[q] * color + ks[q] * k.spec[q] * sc + ka[q] * amb;
        d[q] += e.w * (gg[q] * u);
      }
    }
  }
}

// Phong: the block's colour before the clamp, fog and gain (ShadeRange's sum) into c0, and every
// direction's derivative of it into dcol [K][3][kBlock].
void PhongPartials(const Config& cfg, const Maps& mp, const float* params, const float* lights, int64_t num_lights,
                   const std::vector<Entry>& es, Block& k, int m, float* dcol, float* g, float* h,
                   float (*c0)[kBlock]) {
  const float* front = params;
  const float* backm = params + kMat;
  const float* amb_light = params + 2 * kMat;
  const float* eye = amb_light + 3;
  const float* view_z = eye + 3;
  const float amb_on = cfg.Flag(1) ? 1.0f : 0.0f, em_on = cfg.Flag(0) ? 1.0f : 0.0f;
  for (int i = 0; i < mp.count; ++i) SampleMap(mp.map[i], k, m, k.tex[i]);
  PixelMaterial(cfg, mp, front, backm, k, m);
  Surface(cfg.Flag(5), eye, view_z, k, m);
  for (int c = 0; c < 3; ++c) {
    for (int q = 0; q < m; ++q) k.col[c][q] = 0.0f, k.base[c][q] = 0.0f;
  }
  for (int64_t i = 0; i < num_lights; ++i) {
    AddLight(cfg, front, backm, lights + i * kLight, k, m, true);
    LightPartials(cfg, mp, front, backm, lights + i * kLight, i, es, m, k, dcol, g, h);
  }
  // the ambient and emission terms: k_a I_a and k_e, and the ambient light I_a
  for (const Entry& e : es) {
    const int64_t s = e.slot;
    if (s < 2 * kMat && (s % kMat) < 6) {
      const int field = static_cast<int>(s % kMat) / 3, c = static_cast<int>(s % kMat) % 3;
      const float on = field == 0 ? em_on : amb_on * amb_light[c];
      if (on == 0.0f) continue;
      Side(mp, k, field, c, s >= kMat, m, h);
      Accumulate(dcol + (int64_t{e.j} * 3 + c) * kBlock, e.w * on, h, m);
    } else if (s >= 2 * kMat && s < 2 * kMat + 3 && amb_on != 0.0f) {
      const int c = static_cast<int>(s - 2 * kMat);
      Accumulate(dcol + (int64_t{e.j} * 3 + c) * kBlock, e.w, k.ka[c], m);
    }
  }
  // the colour before the clamp, fog and gain (ShadeRange's sum), and the fog factor
  for (int c = 0; c < 3; ++c) {
    for (int q = 0; q < m; ++q) {
      c0[c][q] = ((k.base[c][q] + (k.ka[c][q] * amb_light[c]) * amb_on) + k.ke[c][q] * em_on) + k.col[c][q];
    }
  }
}

// Gouraud: the interpolated colour (Points': the vertices' colours, lit and clamped in JAX) into
// c0, and each direction's derivative of it, the corners' tangents (corners [K][2][V][3]: front,
// back) interpolated with the same barycentrics, into dcol [K][3][kBlock].
void CornerPartials(const int32_t* tri, int64_t num_verts, const float* corners, int64_t K, const Block& k, int m,
                    float* dcol, float (*c0)[kBlock]) {
  for (int q = 0; q < m; ++q) c0[0][q] = k.nx[q], c0[1][q] = k.ny[q], c0[2][q] = k.nz[q];
  for (int q = 0; q < m; ++q) {
    const int64_t t = k.face[q];
    int64_t v[3];
    for (int i = 0; i < 3; ++i) v[i] = std::min<int64_t>(std::max<int32_t>(tri[3 * t + i], 0), num_verts - 1);
    const int64_t side = k.back[q] > 0 ? 1 : 0;
    const float b0 = k.b0[q], b1 = k.b1[q], b2 = k.b2[q];
    for (int64_t j = 0; j < K; ++j) {
      const float* at = corners + (j * 2 + side) * num_verts * 3;
      for (int c = 0; c < 3; ++c) {
        dcol[(j * 3 + c) * kBlock + q] = (at[3 * v[0] + c] * b0 + at[3 * v[1] + c] * b1) + at[3 * v[2] + c] * b2;
      }
    }
  }
}

// Pixels [p0, p1) of the partials out [K, n, 3] (entries: the nonzero directions' numbers).
DIFFSHADE_CLONES void PartialsRange(const Config& cfg, const Pixels& px, const float* faces, const float* params,
                                     const float* lights, int64_t num_lights, const Maps& mp, const std::vector<Entry>& es, int64_t K,
                                     const int32_t* tri, int64_t num_verts, const float* corners, int64_t n,
                                     int64_t p0, int64_t p1, float* value, float* out) {
  const float* eye = params + 2 * kMat + 3;
  const float* fog = eye + 6;
  const float* background = fog + 6;
  const float* gain = background + 3;
  const int fog_mode = cfg.fog & 3;
  const bool fog_depth = (cfg.fog & 4) != 0;
  std::vector<float> empty(static_cast<size_t>(K * 3), 0.0f);  // an empty pixel's: background times gain
  for (const Entry& e : es) {
    const int64_t s = e.slot - (2 * kMat + 15);
    if (s >= 0 && s < 3) empty[e.j * 3 + s] += e.w * gain[s];
    if (s >= 3 && s < 6) empty[e.j * 3 + s - 3] += e.w * background[s - 3];
  }
  std::vector<float> dcol(static_cast<size_t>(K * 3 * kBlock)), dfog(static_cast<size_t>(K * kBlock));
  float g[kBlock] = {}, h[kBlock] = {}, c0[3][kBlock], ca[3][kBlock], cb[3][kBlock], cc[3][kBlock], ho[3][kBlock];
  Block k;
  std::memset(k.ke, 0, sizeof(k.ke)), std::memset(k.ka, 0, sizeof(k.ka)), std::memset(k.kd, 0, sizeof(k.kd));
  std::memset(k.ks, 0, sizeof(k.ks)), std::memset(k.sh, 0, sizeof(k.sh));
  int64_t col = px.grid ? p0 % px.width : 0, row = px.grid ? p0 / px.width : 0;
  for (int64_t b0 = p0; b0 < p1; b0 += kBlock) {
    const int64_t b1 = std::min(b0 + kBlock, p1);
    auto empty_run = [&](int64_t p, int64_t r) {  // each plane's run of the background's value
      for (int64_t q = p; q < r; ++q) {
        for (int c = 0; c < 3; ++c) value[3 * q + c] = background[c] * gain[c];
      }
      for (int64_t j = 0; j < K; ++j) {
        const float e0 = empty[j * 3], e1 = empty[j * 3 + 1], e2 = empty[j * 3 + 2];
        float* o = out + (j * n + p) * 3;
        for (int64_t q = 0; q < r - p; ++q) o[3 * q] = e0, o[3 * q + 1] = e1, o[3 * q + 2] = e2;
      }
    };
    const int m = Points(px, faces, cfg.Flag(4), cfg.Flag(8), mp, b0, b1, col, row, k, empty_run);
    std::fill(dcol.begin(), dcol.end(), 0.0f);
    if (cfg.Flag(8)) {
      CornerPartials(tri, num_verts, corners, K, k, m, dcol.data(), c0);
    } else {
      PhongPartials(cfg, mp, params, lights, num_lights, es, k, m, dcol.data(), g, h, c0);
    }
    std::fill(dfog.begin(), dfog.end(), 0.0f);
    float* __restrict f = k.fog;
    for (int q = 0; q < m; ++q) f[q] = 1.0f;
    if (fog_mode != 0) {
      FogFactor(fog_mode, fog_depth, fog, eye, k, m, h, f);  // (h: the fog's distance)
      const float start = fog[3], end = fog[4], rho = fog[5], den = end - start;
      for (const Entry& e : es) {  // d f / d (start, end, density)
        const int64_t s = e.slot - (2 * kMat + 12);
        if (s < 0 || s >= 3) continue;
        float* __restrict df = dfog.data() + int64_t{e.j} * kBlock;
        for (int q = 0; q < m; ++q) {
          const float d = h[q];
          float v = 0.0f;
          if (fog_mode == 1) {
            const float t = den > 0 ? (end - d) / den : 0.0f;
            const bool in = den > 0 && t > 0 && t < 1;
            v = !in ? 0.0f : s == 0 ? t / den : s == 1 ? (d - start) / (den * den) : 0.0f;
          } else if (s == 2) {
            v = fog_mode == 2 ? -d * f[q] : -2.0f * rho * d * d * f[q];
          }
          df[q] += e.w * v;
        }
      }
    }
    // through the clamp, fog, clamp after and gain: out = A dcol + B dfog + C dfog_colour + x3 dgain
    for (int c = 0; c < 3; ++c) {
      const float fc = fog[c], gc = gain[c];
      for (int q = 0; q < m; ++q) {
        const float x = c0[c][q];
        const float p1 = cfg.Flag(6) ? ((x > 0 && x < 1) ? 1.0f : 0.0f) : 1.0f;
        const float x1 = cfg.Flag(6) ? Clip01(x) : x;
        const float x2 = fog_mode != 0 ? f[q] * x1 + (1.0f - f[q]) * fc : x1;
        const float p3 = gc * (cfg.Flag(7) ? ((x2 > 0 && x2 < 1) ? 1.0f : 0.0f) : 1.0f);
        ca[c][q] = p3 * f[q] * p1;
        cb[c][q] = fog_mode != 0 ? p3 * (x1 - fc) : 0.0f;
        cc[c][q] = fog_mode != 0 ? p3 * (1.0f - f[q]) : 0.0f;
        c0[c][q] = cfg.Flag(7) ? Clip01(x2) : x2;
      }
    }
    for (int q = 0; q < m; ++q) {  // the value (ShadeRange's, operation for operation)
      float* v = value + 3 * k.pix[q];
      v[0] = c0[0][q] * gain[0], v[1] = c0[1][q] * gain[1], v[2] = c0[2][q] * gain[2];
    }
    for (int64_t j = 0; j < K; ++j) {
      float dfc[3] = {0.0f, 0.0f, 0.0f}, dgain[3] = {0.0f, 0.0f, 0.0f};
      for (const Entry& e : es) {
        const int64_t s = e.slot - (2 * kMat + 9);
        if (e.j == j && s >= 0 && s < 3) dfc[s] += e.w;
        if (e.j == j && s >= 9 && s < 12) dgain[s - 9] += e.w;
      }
      const float* __restrict df = dfog.data() + j * kBlock;
      for (int c = 0; c < 3; ++c) {
        const float* __restrict dc = dcol.data() + (j * 3 + c) * kBlock;
        float* __restrict hc = ho[c];
        for (int q = 0; q < m; ++q) hc[q] = ((ca[c][q] * dc[q] + cb[c][q] * df[q]) + cc[c][q] * dfc[c]) + c0[c][q] * dgain[c];
      }
      float* o = out + j * n * 3;
      for (int q = 0; q < m; ++q) {
        float* p = o + k.pix[q] * 3;
        p[0] = ho[0][q], p[1] = ho[1][q], p[2] = ho[2][q];
      }
    }
  }
}

// The face table (kFace floats per face) of faces [f0, f1): the edge functions of
// _raster.py::_face_planes from the clip-space vertices, the corners' clip w, D, and the corners'
// normals and positions.
void FaceTable(const float* clip, const int32_t* tri, const float* normals, const float* points, const float* back,
               int64_t num_verts, int64_t f0, int64_t f1, float* table) {
  for (int64_t f = f0; f < f1; ++f) {
    float* g = table + f * kFace;
    float X[3], Y[3], W[3];
    int64_t v[3];
    for (int j = 0; j < 3; ++j) {
      v[j] = std::min<int64_t>(std::max<int32_t>(tri[3 * f + j], 0), num_verts - 1);
      const float* c = clip + 4 * v[j];
      X[j] = c[0], Y[j] = c[1], W[j] = c[3];
    }
    for (int i = 0; i < 3; ++i) {
      const int a = (i + 1) % 3, b = (i + 2) % 3;
      g[3 * i] = X[a] * Y[b] - X[b] * Y[a];
      g[3 * i + 1] = W[b] * Y[a] - W[a] * Y[b];
      g[3 * i + 2] = X[b] * W[a] - X[a] * W[b];
    }
    for (int j = 0; j < 3; ++j) g[9 + j] = W[j];
    const float det = (X[0] * (Y[1] * W[2] - Y[2] * W[1]) - Y[0] * (X[1] * W[2] - X[2] * W[1])) +
                      W[0] * (X[1] * Y[2] - X[2] * Y[1]);
    g[12] = det;
    for (int j = 0; j < 3; ++j) {
      for (int c = 0; c < 3; ++c) {
        g[13 + 3 * j + c] = normals[3 * v[j] + c];
        g[22 + 3 * j + c] = points[3 * v[j] + c];
        g[32 + 3 * j + c] = back[3 * v[j] + c];
      }
    }
    g[31] = det > 0 ? 1.0f : 0.0f;
  }
}

// The maps' description (layout above Maps), checked against the texels' size: nullptr, or what
// is wrong. The levels' offsets are into the scratch PackMaps fills (its size in *packed), each
// level with its border.
const char* ReadMaps(const int32_t* a, int64_t n, int64_t num_texels, Maps& mp, int64_t* packed) {
  *packed = 0;
  if (n == 0) return nullptr;
  if (n < kMapsHeader) return "maps: too short";
  for (int f = 0; f < 5; ++f) mp.field[f] = a[f];
  mp.parts = a[5];
  for (int g = 0; g < kMaxParts; ++g) mp.part_map[g] = a[6 + g];
  if (a[10] <= 0 || a[11] <= 0) return "maps: bad camera size";
  mp.sx = 2.0f / static_cast<float>(a[10]), mp.sy = 2.0f / static_cast<float>(a[11]);
  mp.count = a[12];
  if (mp.count < 1 || mp.count > kMaxMaps || mp.parts < 0 || mp.parts > kMaxParts) return "maps: bad counts";
  if (n != kMapsHeader + mp.count * kMapInts) return "maps: bad length";
  for (int f = 0; f < 5; ++f) {
    if (mp.field[f] < -1 || mp.field[f] >= mp.count) return "maps: bad field";
  }
  for (int g = 0; g < mp.parts; ++g) {
    if (mp.part_map[g] < 0 || mp.part_map[g] >= mp.count) return "maps: bad part";
  }
  int64_t given = 0;
  for (int i = 0; i < mp.count; ++i) {
    const int32_t* d = a + kMapsHeader + i * kMapInts;
    Map& t = mp.map[i];
    t.channels = d[0], t.clamp = d[1] != 0, t.trilinear = d[2] != 0, t.given = given;
    int w = d[3], h = d[4];
    if ((t.channels != 1 && t.channels != 3) || w < 1 || h < 1) return "maps: bad map";
    mp.derivatives = mp.derivatives || t.trilinear;
    if ((int64_t{w} + 2) * (int64_t{h} + 2) * t.channels >= (int64_t{1} << 31)) {
      return "maps: a map of more than 2^31 values";
    }
    given += int64_t{w} * h * t.channels;
    t.levels = 0;
    for (;;) {  // _texture.mip_pyramid's sizes: halved (rounding up) to 1 x 1
      t.lv[t.levels++] = Level{*packed, w, h};
      *packed += t.lv[t.levels - 1].Stride(t.channels) * (h + 2);
      if (!t.trilinear || (w == 1 && h == 1)) break;
      if (t.levels == kMaxLevels) return "maps: too many levels";
      w = (w + 1) / 2, h = (h + 1) / 2;
    }
  }
  *packed += 4;  // (slack: Blend's loads of four floats at a level's last texel)
  return given == num_texels ? nullptr : "maps: the texels do not match the maps' sizes";
}

// Rows [y0, y1) of a level (b, its first texel inside the border at dst) from the one before (a,
// at src, whose rows are src_stride floats apart; C channels): 2 x 2 box averages
// (_texture.mip_pyramid: rows first, then columns, an odd last row or column averaged with
// itself; the same sums in the same order). Where copy is given, the rows of a that are read are
// also copied there (a's texels inside its border: level 0 packed from the texels as they are
// read, in cache). C is a template argument so that a texel's channels are known to the
// compiler: with C and the column pairs' bound at run time, a 256² colour map's levels took
// 0.36 ms of a render's CPU time, and 0.17 ms with them known.
template <int C>
void DownsampleRows(const float* src, int64_t src_stride, const Level& a, float* dst, const Level& b, int y0, int y1,
                    float* copy) {
  const int64_t row = int64_t{a.w} * C;
  std::vector<float> sum(static_cast<size_t>(row));  // a pair of rows averaged (a loop that vectorises)
  const int pairs = a.w / 2;  // (an odd last column: averaged with itself, after them)
  for (int y = y0; y < y1; ++y) {
    const int i0 = a.h > 1 ? 2 * y : 0, i1 = a.h > 1 ? std::min(2 * y + 1, a.h - 1) : 0;
    const float* r0 = src + i0 * src_stride;
    const float* r1 = src + i1 * src_stride;
    if (copy) {
      std::memcpy(copy + i0 * a.Stride(C), r0, row * sizeof(float));
      if (i1 != i0) std::memcpy(copy + i1 * a.Stride(C), r1, row * sizeof(float));
    }
    const float* l = r0;
    if (a.h > 1) {
      float* __restrict t = sum.data();
      for (int64_t i = 0; i < row; ++i) t[i] = 0.5f * (r0[i] + r1[i]);
      l = t;
    }
    float* __restrict out = dst + y * b.Stride(C);
    if (a.w == 1) {
      for (int c = 0; c < C; ++c) out[c] = l[c];
      continue;
    }
    for (int x = 0; x < pairs; ++x) {
      for (int c = 0; c < C; ++c) out[x * C + c] = 0.5f * (l[2 * x * C + c] + l[(2 * x + 1) * C + c]);
    }
    if (a.w % 2) {
      for (int c = 0; c < C; ++c) out[pairs * C + c] = 0.5f * (l[2 * pairs * C + c] + l[2 * pairs * C + c]);
    }
  }
}

void Downsample(const float* src, int64_t src_stride, const Level& a, float* dst, const Level& b, int C, int y0,
                int y1, float* copy) {
  if (C == 3) return DownsampleRows<3>(src, src_stride, a, dst, b, y0, y1, copy);
  DownsampleRows<1>(src, src_stride, a, dst, b, y0, y1, copy);
}

// A level's border (the level at base, its texels written): each row's first and last texel,
// then the top and bottom rows (corners included), copied from the other side (repeating) or the
// edge (clamping).
void Border(float* base, const Level& a, int C, bool clamp) {
  const int64_t stride = a.Stride(C);
  for (int y = 1; y <= a.h; ++y) {
    float* r = base + y * stride;
    std::memcpy(r, r + (clamp ? 1 : a.w) * C, C * sizeof(float));
    std::memcpy(r + (int64_t{a.w} + 1) * C, r + (clamp ? a.w : 1) * C, C * sizeof(float));
  }
  std::memcpy(base, base + (clamp ? 1 : a.h) * stride, stride * sizeof(float));
  std::memcpy(base + (int64_t{a.h} + 1) * stride, base + (clamp ? a.h : 1) * stride, stride * sizeof(float));
}

// How a level's rows are split among threads (PackMaps' and Packed's): into RowParts parts, one
// for a small level and one per thread for a large one; part q begins at row RowsFrom(a, q, parts).
int64_t RowParts(const Level& a, int64_t nthreads) {
  return int64_t{a.w} * a.h < 16384 ? 1 : std::min<int64_t>(nthreads, a.h);
}
inline int RowsFrom(const Level& a, int64_t q, int64_t parts) { return static_cast<int>(a.h * q / parts); }

// Each map's levels in the scratch (laid out by ReadMaps): level 0 copied from the texels, level
// 1 built from the texels as they are copied, the others from the level before (Downsample),
// each then given its border (a large level's rows in threads: level 0's split as level 1's).
void PackMaps(ffi::ThreadPool& pool, int64_t nthreads, Maps& mp, const float* texels, float* packed) {
  for (int i = 0; i < mp.count; ++i) {
    Map& t = mp.map[i];
    const int C = t.channels;
    for (int j = 0; j < t.levels; ++j) t.base[j] = packed + t.lv[j].off;
    for (int j = 0; j < t.levels; ++j) {
      const Level& b = t.lv[j];
      float* inside = packed + b.off + b.Inside(C);
      if (j == 1) {  // (built with level 0)
        Border(packed + b.off, b, C, t.clamp);
        continue;
      }
      const int64_t parts = RowParts(b, nthreads);
      diffshade::ParallelFor(pool, parts, [&](int64_t q) {
        if (j > 0) {
          const Level& a = t.lv[j - 1];
          Downsample(t.base[j - 1] + a.Inside(C), a.Stride(C), a, inside, b, C, RowsFrom(b, q, parts),
                     RowsFrom(b, q + 1, parts), nullptr);
          return;
        }
        const float* src = texels + t.given;
        const int64_t row = int64_t{b.w} * C;
        if (t.levels > 1) {  // (level 1's rows [y0, y1) read and copy level 0's rows 2 y0 to 2 y1)
          const Level& c = t.lv[1];
          Downsample(src, row, b, packed + c.off + c.Inside(C), c, C, RowsFrom(c, q, parts), RowsFrom(c, q + 1, parts),
                     inside);
          return;
        }
        for (int y = RowsFrom(b, q, parts); y < RowsFrom(b, q + 1, parts); ++y) {
          std::memcpy(inside + y * b.Stride(C), src + y * row, row * sizeof(float));
        }
      });
      Border(packed + b.off, b, C, t.clamp);
    }
  }
}

// Whether the scratch's levels 0 (at packed, laid out by ReadMaps) hold the texels: their bits,
// row by row (a first difference ends the comparison; a large level's rows in threads, as
// PackMaps': alone, a 256² colour map's comparison was 0.2 ms of a 512² render's 8).
bool Packed(ffi::ThreadPool& pool, int64_t nthreads, const Maps& mp, const float* texels, const float* packed) {
  for (int i = 0; i < mp.count; ++i) {
    const Map& t = mp.map[i];
    const Level& a = t.lv[0];
    const int64_t row = int64_t{a.w} * t.channels, stride = a.Stride(t.channels);
    const float* level = packed + a.off + a.Inside(t.channels);
    const int64_t parts = RowParts(a, nthreads);
    std::atomic<bool> differ{false};
    diffshade::ParallelFor(pool, parts, [&](int64_t q) {
      const int y0 = RowsFrom(a, q, parts), y1 = RowsFrom(a, q + 1, parts);
      for (int y = y0; y < y1 && !differ.load(std::memory_order_relaxed); ++y) {
        if (std::memcmp(level + y * stride, texels + t.given + y * row, row * sizeof(float)) != 0) differ = true;
      }
    });
    if (differ) return false;
  }
  return true;
}

// Maps packed (PackMaps) for a description of the maps (the int32 input) and the texels that
// level 0 holds. The last kKept packed, by any thread, are kept: a call whose maps are one of
// theirs (the same description, the same texel bits: Packed) reads it (a render of several
// views, a fit's steps that leave the maps), one with other maps packs its own (into the memory
// of the least recent, where no call holds it) and keeps it. Calls hold what they read. What is
// kept stays under kKeptFloats (256 MB: a 4096² colour map's levels are 268 MB, and are not kept).
struct Packing {
  std::vector<int32_t> desc;
  std::vector<float> levels;
};
constexpr size_t kKept = 4;
constexpr size_t kKeptFloats = size_t{64} << 20;
std::mutex packing_lock;
std::vector<std::shared_ptr<Packing>> packing_kept;  // (the most recent first)

bool Holds(ffi::ThreadPool& pool, int64_t nthreads, const Packing& e, const Maps& mp, const int32_t* desc, int64_t nd,
           const float* texels, int64_t packed) {
  return e.levels.size() == static_cast<size_t>(packed) && e.desc.size() == static_cast<size_t>(nd) &&
         std::equal(desc, desc + nd, e.desc.begin()) && Packed(pool, nthreads, mp, texels, e.levels.data());
}

std::shared_ptr<const Packing> Pack(ffi::ThreadPool& pool, int64_t nthreads, Maps& mp, const int32_t* desc, int64_t nd,
                                    const float* texels, int64_t packed) {
  std::shared_ptr<Packing> mine;
  {
    std::vector<std::shared_ptr<Packing>> kept;
    {
      std::lock_guard<std::mutex> hold(packing_lock);
      kept = packing_kept;
    }
    for (auto& e : kept) {
      if (Holds(pool, nthreads, *e, mp, desc, nd, texels, packed)) {
        mine = e;
        break;
      }
    }
  }
  if (mine) {
    std::lock_guard<std::mutex> hold(packing_lock);
    auto at = std::find(packing_kept.begin(), packing_kept.end(), mine);
    if (at != packing_kept.end()) std::rotate(packing_kept.begin(), at, at + 1);
  } else {
    {
      std::lock_guard<std::mutex> hold(packing_lock);
      if (packing_kept.size() == kKept) {
        if (packing_kept.back().use_count() == 1) mine = std::move(packing_kept.back());  // (no call holds it)
        packing_kept.pop_back();
      }
    }
    if (!mine) mine = std::make_shared<Packing>();
    mine->levels.resize(static_cast<size_t>(packed));
    PackMaps(pool, nthreads, mp, texels, mine->levels.data());
    std::memset(mine->levels.data() + packed - 4, 0, 4 * sizeof(float));  // (the slack)
    mine->desc.assign(desc, desc + nd);
    std::lock_guard<std::mutex> hold(packing_lock);
    packing_kept.insert(packing_kept.begin(), mine);
    if (packing_kept.size() > kKept) packing_kept.pop_back();
    size_t kept_floats = 0;
    for (const auto& e : packing_kept) kept_floats += e->levels.capacity();
    while (!packing_kept.empty() && kept_floats > kKeptFloats) {  // (the least recent first, mine last)
      kept_floats -= packing_kept.back()->levels.capacity();
      packing_kept.pop_back();
    }
  }
  for (int i = 0; i < mp.count; ++i) {
    for (int j = 0; j < mp.map[i].levels; ++j) mp.map[i].base[j] = mine->levels.data() + mp.map[i].lv[j].off;
  }
  return mine;
}

// The inputs both kernels share: their shapes checked, the maps read (their pyramids built)
// and the face tables, FaceTable's and (maps) FaceMap's (in scratch kept per calling thread
// between calls; every entry is written).
struct Scene {
  Pixels px = {};  // (its n: the number of pixels)
  int64_t num_lights = 0, nthreads = 1;
  Maps mp;
  std::shared_ptr<const Packing> packing;  // (what mp's levels point into)
  const float* table = nullptr;
};

const char* Prepare(ffi::ThreadPool& pool, ffi::Buffer<ffi::S32>& ids, ffi::Buffer<ffi::F32>& xs,
                    ffi::Buffer<ffi::F32>& ys, ffi::Buffer<ffi::F32>& clip, ffi::Buffer<ffi::S32>& tri,
                    ffi::Buffer<ffi::F32>& normals, ffi::Buffer<ffi::F32>& points, ffi::Buffer<ffi::F32>& back,
                    ffi::Buffer<ffi::F32>& params, ffi::Buffer<ffi::F32>& lights, ffi::Buffer<ffi::F32>& uv,
                    ffi::Buffer<ffi::F32>& texels, ffi::Buffer<ffi::S32>& maps, ffi::Buffer<ffi::F32>& parts,
                    int32_t grid, bool two_sided, Scene& sc) {
  const int64_t n = ids.element_count();
  const int64_t num_verts = clip.element_count() / 4, num_faces = tri.element_count() / 3;
  if (params.element_count() != kParams || lights.element_count() % kLight != 0 ||
      normals.element_count() != 3 * num_verts || points.element_count() != 3 * num_verts ||
      back.element_count() != 3 * num_verts || num_verts == 0) {
    return "bad shapes";
  }
  const int64_t width = xs.element_count();
  if (grid ? width * ys.element_count() != n : (width != n || ys.element_count() != n)) {
    return "pixel centres do not match the ids";
  }
  sc.px = Pixels{ids.typed_data(), xs.typed_data(), ys.typed_data(), grid != 0, width, n};
  sc.num_lights = lights.element_count() / kLight;
  unsigned hw = std::thread::hardware_concurrency();
  sc.nthreads = n < 16384 ? 1 : std::min<int64_t>(hw == 0 ? 1 : hw, 8);  // (small images: one thread)
  Maps& mp = sc.mp;
  int64_t packed = 0;
  if (const char* bad = ReadMaps(maps.typed_data(), maps.element_count(), texels.element_count(), mp, &packed)) {
    return bad;
  }
  if (mp.any()) {
    if (uv.element_count() != 2 * num_verts || parts.element_count() != mp.parts * 2 * num_verts * 3) {
      return "texture coordinates or parts do not match the mesh";
    }
    sc.packing = Pack(pool, sc.nthreads, mp, maps.typed_data(), maps.element_count(), texels.typed_data(), packed);
    mp.face_floats = kFaceMapHead + 9 * mp.parts;
  }
  thread_local std::vector<float> table, map_table;
  table.resize(static_cast<size_t>(num_faces * kFace));
  map_table.resize(static_cast<size_t>(num_faces * mp.face_floats));
  float* tab = table.data();
  float* mtab = map_table.data();
  mp.faces = mtab;
  const int64_t ft = num_faces < 4096 ? 1 : sc.nthreads;
  diffshade::ParallelFor(pool, ft, [&](int64_t k) {
    const int64_t f0 = num_faces * k / ft, f1 = num_faces * (k + 1) / ft;
    FaceTable(clip.typed_data(), tri.typed_data(), normals.typed_data(), points.typed_data(), back.typed_data(),
              num_verts, f0, f1, tab);
    if (!mp.any()) return;
    for (int64_t f = f0; f < f1; ++f) {
      FaceMap::Of(mp, uv.typed_data(), tri.typed_data(), parts.typed_data(), num_verts, two_sided, f,
                  tab + f * kFace, mtab + f * mp.face_floats);
    }
  });
  sc.table = tab;
  return nullptr;
}

ffi::Error ShadeImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::S32> ids, ffi::Buffer<ffi::F32> xs,
                     ffi::Buffer<ffi::F32> ys, ffi::Buffer<ffi::F32> clip, ffi::Buffer<ffi::S32> tri,
                     ffi::Buffer<ffi::F32> normals, ffi::Buffer<ffi::F32> points, ffi::Buffer<ffi::F32> back,
                     ffi::Buffer<ffi::F32> params, ffi::Buffer<ffi::F32> lights, ffi::Buffer<ffi::F32> uv,
                     ffi::Buffer<ffi::F32> texels, ffi::Buffer<ffi::S32> maps, ffi::Buffer<ffi::F32> parts,
                     ffi::ResultBuffer<ffi::F32> out, int32_t specular,
                     int32_t fresnel, int32_t flags, int32_t fog, int32_t grid) {
  const Config cfg{specular, fresnel, flags, fog};
  Scene sc;
  if (const char* bad = Prepare(pool, ids, xs, ys, clip, tri, normals, points, back, params, lights, uv, texels, maps,
                                parts, grid, cfg.Flag(4), sc)) {
    return ffi::Error::InvalidArgument(std::string("diffshade_shade: ") + bad);
  }
  if (out->element_count() != 3 * sc.px.n) return ffi::Error::InvalidArgument("diffshade_shade: bad shapes");
  const int64_t n = sc.px.n, chunks = sc.nthreads * 4;
  diffshade::ParallelFor(pool, chunks, [&](int64_t k) {
    ShadeRange(cfg, sc.px, sc.table, params.typed_data(), lights.typed_data(), sc.num_lights, sc.mp, n * k / chunks,
               n * (k + 1) / chunks, out->typed_data());
  });
  return ffi::Error::Success();
}

// The render [N, 3] (ShadeImpl's) and its partials [K, N, 3] along the K directions dirs
// [K, kParams + L kLight] of its numbers, and (Gouraud) of its vertices' colours (corners).
ffi::Error PartialsImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::S32> ids, ffi::Buffer<ffi::F32> xs,
                        ffi::Buffer<ffi::F32> ys, ffi::Buffer<ffi::F32> clip, ffi::Buffer<ffi::S32> tri,
                        ffi::Buffer<ffi::F32> normals, ffi::Buffer<ffi::F32> points, ffi::Buffer<ffi::F32> back,
                        ffi::Buffer<ffi::F32> params, ffi::Buffer<ffi::F32> lights, ffi::Buffer<ffi::F32> uv,
                        ffi::Buffer<ffi::F32> texels, ffi::Buffer<ffi::S32> maps, ffi::Buffer<ffi::F32> parts,
                        ffi::Buffer<ffi::F32> dirs, ffi::Buffer<ffi::F32> corners, ffi::ResultBuffer<ffi::F32> value,
                        ffi::ResultBuffer<ffi::F32> out, int32_t specular,
                        int32_t fresnel, int32_t flags, int32_t fog, int32_t grid) {
  const Config cfg{specular, fresnel, flags, fog};
  Scene sc;
  if (const char* bad = Prepare(pool, ids, xs, ys, clip, tri, normals, points, back, params, lights, uv, texels, maps,
                                parts, grid, cfg.Flag(4), sc)) {
    return ffi::Error::InvalidArgument(std::string("diffshade_shade_partials: ") + bad);
  }
  const int64_t n = sc.px.n, row = kParams + sc.num_lights * kLight;
  const int64_t K = dirs.element_count() / row;
  const int64_t num_verts = clip.element_count() / 4;
  const bool gouraud = cfg.Flag(8);
  if (K * row != dirs.element_count() || out->element_count() != K * n * 3 || value->element_count() != n * 3 ||
      corners.element_count() != (gouraud ? K * 2 * num_verts * 3 : 0) || (gouraud && sc.mp.any())) {
    return ffi::Error::InvalidArgument("diffshade_shade_partials: bad shapes (or Gouraud shading with maps)");
  }
  std::vector<Entry> es;  // the directions' nonzero numbers
  const float* d = dirs.typed_data();
  for (int64_t j = 0; j < K; ++j) {
    for (int64_t slot = 0; slot < row; ++slot) {
      const float w = d[j * row + slot];
      if (w == 0.0f) continue;
      const bool pixel = slot >= 2 * kMat + 9 && slot < kParams;  // fog, background, gain
      if (!Supported(slot) || (gouraud && !pixel)) {  // (Gouraud: the rest lit at the vertices: corners)
        return ffi::Error::InvalidArgument("diffshade_shade_partials: a direction moves a number it does not differentiate");
      }
      es.push_back(Entry{static_cast<int>(slot), static_cast<int>(j), w});
    }
  }
  const int64_t chunks = sc.nthreads * 4;
  diffshade::ParallelFor(pool, chunks, [&](int64_t k) {
    PartialsRange(cfg, sc.px, sc.table, params.typed_data(), lights.typed_data(), sc.num_lights, sc.mp, es, K,
                  tri.typed_data(), num_verts, corners.typed_data(), n, n * k / chunks, n * (k + 1) / chunks,
                  value->typed_data(), out->typed_data());
  });
  return ffi::Error::Success();
}

}  // namespace

namespace {

// The inputs both kernels take (Prepare's), in their order.
auto SceneInputs() {
  return ffi::Ffi::Bind()
      .Ctx<ffi::ThreadPool>()
      .Arg<ffi::Buffer<ffi::S32>>()   // ids [N]
      .Arg<ffi::Buffer<ffi::F32>>()   // xs [W] (grid) or [N]
      .Arg<ffi::Buffer<ffi::F32>>()   // ys [H] (grid) or [N]
      .Arg<ffi::Buffer<ffi::F32>>()   // clip-space vertices [V, 4]
      .Arg<ffi::Buffer<ffi::S32>>()   // faces [F, 3]
      .Arg<ffi::Buffer<ffi::F32>>()   // vertex normals [V, 3]
      .Arg<ffi::Buffer<ffi::F32>>()   // vertex positions [V, 3]
      .Arg<ffi::Buffer<ffi::F32>>()   // Gouraud: back colours [V, 3]
      .Arg<ffi::Buffer<ffi::F32>>()   // params [kParams]
      .Arg<ffi::Buffer<ffi::F32>>()   // lights [L, kLight]
      .Arg<ffi::Buffer<ffi::F32>>()   // texture coordinates [V, 2] (or none)
      .Arg<ffi::Buffer<ffi::F32>>()   // the maps' texels, one after the other
      .Arg<ffi::Buffer<ffi::S32>>()   // the maps' description (Maps)
      .Arg<ffi::Buffer<ffi::F32>>();  // Gouraud: mapped parts [G, 2, V, 3]
}

// The static configuration both kernels take (Config's, and whether the pixels are a grid), last.
template <class Binding>
auto Switches(Binding&& b) {
  return std::forward<Binding>(b)
      .template Attr<int32_t>("specular")
      .template Attr<int32_t>("fresnel")
      .template Attr<int32_t>("flags")
      .template Attr<int32_t>("fog")
      .template Attr<int32_t>("grid");
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffshadeShade, ShadeImpl,
                              Switches(SceneInputs().Ret<ffi::Buffer<ffi::F32>>()));  // out [N, 3]

XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffshadeShadePartials, PartialsImpl,
                              Switches(SceneInputs()
                                           .Arg<ffi::Buffer<ffi::F32>>()    // directions [K, kParams + L kLight]
                                           .Arg<ffi::Buffer<ffi::F32>>()    // Gouraud: corners' tangents [K, 2, V, 3]
                                           .Ret<ffi::Buffer<ffi::F32>>()    // the render [N, 3]
                                           .Ret<ffi::Buffer<ffi::F32>>()));  // partials [K, N, 3]
