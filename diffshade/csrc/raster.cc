// diffshade native visibility kernel (CPU), registered with XLA through jax.ffi.
//
// It implements the same set-up and per-pixel test as the pure-JAX tiled rasterizer
// (diffshade/_raster.py), operation for operation: a pixel (column i, row j) with
// qx = 2i + 1, qy = 2j + 1 is covered by triangle f when, for each edge k,
//     E_k = c0 + cy qy + cx qx  >  0,  or  == 0 and the edge owns ties,
// and the depth d (DepthAt: the vertices' depths' mean weighted by w_k E_k) is in [-1, 1].
// Fragments are kept per pixel as the K nearest by (depth, triangle id).
//
// Bit-for-bit agreement with XLA: XLA may contract a*b + c into a fused multiply-add, so every
// product here is exact (factors split into short pieces, see Mul and Plane), which makes
// contraction irrelevant; additions happen in the same order as in _raster.py; and denormals
// are flushed to zero (FTZ/DAZ) as XLA's CPU backend does. Compiled with -ffp-contract=off, and
// with -fno-trapping-math, which lets the compiler vectorise the branch-free row test (it
// changes no result: IEEE operations round the same in vector registers).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

#if defined(__SSE2__) || defined(__x86_64__)
#include <xmmintrin.h>
#define DIFFSHADE_X86 1
#endif

#include "parallel.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// Flush denormals to zero (results and inputs) for the lifetime of the object, as XLA does.
class ScopedFlushDenormals {
 public:
  ScopedFlushDenormals() {
#if defined(DIFFSHADE_X86)
    saved_ = _mm_getcsr();
    _mm_setcsr(saved_ | 0x8040);  // FTZ | DAZ
#elif defined(__aarch64__)
    uint64_t fpcr;
    __asm__ __volatile__("mrs %0, fpcr" : "=r"(fpcr));
    saved_ = fpcr;
    fpcr |= (1ull << 24);  // FZ
    __asm__ __volatile__("msr fpcr, %0" : : "r"(fpcr));
#endif
  }
  ~ScopedFlushDenormals() {
#if defined(DIFFSHADE_X86)
    _mm_setcsr(static_cast<unsigned>(saved_));
#elif defined(__aarch64__)
    __asm__ __volatile__("msr fpcr, %0" : : "r"(saved_));
#endif
  }

 private:
  uint64_t saved_ = 0;
};

// a truncated to its leading `keep` significant bits; the remainder a - hi is exact.
inline float Trunc(float a, int keep) {
  uint32_t bits;
  std::memcpy(&bits, &a, 4);
  bits &= static_cast<uint32_t>(0xFFFFFFFFull << (24 - keep));
  float hi;
  std::memcpy(&hi, &bits, 4);
  return hi;
}

// a * b as four exact 12 x 12-bit partial products, summed in the order of _raster.py::_xmul.
inline float Mul(float a, float b) {
  const float ah = Trunc(a, 12), al = a - ah, bh = Trunc(b, 12), bl = b - bh;
  return (ah * bh + (ah * bl + al * bh)) + al * bl;
}

// Pieces of at most `keep` bits (see _raster.py::_pieces); count is 2 or 3.
struct Pieces {
  float p[3];
};
inline Pieces Split(float a, int keep, int count) {
  Pieces out{{0.0f, 0.0f, 0.0f}};
  for (int k = 0; k < count - 1; ++k) {
    const float hi = Trunc(a, keep);
    out.p[k] = hi;
    a = a - hi;
  }
  out.p[count - 1] = a;
  return out;
}

// A plane c0 + cx qx + cy qy with pre-split coefficients (_raster.py::_plane_eval).
struct Plane {
  float c0;
  Pieces x, y;
};
// The y terms first, then the x terms (_raster.py::_plane_eval): along a row the first part is
// one value (RowPart), and each pixel adds only its x terms (XPart).
template <int kCount>
inline float RowPart(const Plane& pl, float qy) {
  float e = pl.c0;
  for (int k = 0; k < kCount; ++k) e = e + pl.y.p[k] * qy;
  return e;
}
template <int kCount>
inline float XPart(const Plane& pl, float e, float qx) {
  for (int k = 0; k < kCount; ++k) e = e + pl.x.p[k] * qx;
  return e;
}
template <int kCount>
inline float Eval(const Plane& pl, float qx, float qy) {
  return XPart<kCount>(pl, RowPart<kCount>(pl, qy), qx);
}

// A triangle's depth weights (_raster.py::_depth_weights, computed in Setup): a reference depth
// d0 and, cut to 12 bits, dz_k = z_k - d0 w_k and w_k.
struct Depth {
  float d0, dz[3], w[3];
};
// The depth d = d0 + N / W at a pixel with edge functions e0..e2, N = sum_k dz_k E_k and
// W = sum_k w_k E_k (E_k cut to 12 bits, so each product is exact), and whether the point is in
// front of the eye (W > 0) and between the near and far planes (_raster.py::_depth: the weighted
// mean of the vertices' depths, accurate to float32 rounding for a triangle seen edge-on too).
inline bool DepthAt(const Depth& dp, float e0, float e1, float e2, float* d) {
  const float h0 = Trunc(e0, 12), h1 = Trunc(e1, 12), h2 = Trunc(e2, 12);
  const float n = (dp.dz[0] * h0 + dp.dz[1] * h1) + dp.dz[2] * h2;
  const float ww = (dp.w[0] * h0 + dp.w[1] * h1) + dp.w[2] * h2;
  const bool front = ww > 0;
  *d = dp.d0 + n / (front ? ww : 1.0f);
  return front & (*d >= -1.0f) & (*d <= 1.0f);
}

// Bits per piece and piece count (_raster.py::_piece_plan).
inline void PiecePlan(int64_t height, int64_t width, int* keep, int* count) {
  int64_t q = 2 * std::max(height, width) - 1;
  int qbits = 0;
  while (q > 0) { ++qbits; q >>= 1; }
  *keep = 24 - qbits;
  *count = (24 + *keep - 1) / *keep;
}

// Insert the fragment (d, f) into pixel pix's sorted list of K (depth, id); ids arrive in
// increasing order, so equal depths keep the earlier (smaller) id first. A depth that is not
// below the list's last (+inf: not covered; NaN) is not inserted.
inline void Insert(float d, int64_t pix, int64_t f, int64_t layers, int64_t stride, float* depth_buf,
                   int32_t* ids) {
  float* dl = depth_buf + pix * layers;
  int32_t* il = ids + pix;  // stride height * width between layers
  if (!(d < dl[layers - 1])) return;
  int64_t k = layers - 1;
  while (k > 0 && dl[k - 1] > d) {
    dl[k] = dl[k - 1];
    il[k * stride] = il[(k - 1) * stride];
    --k;
  }
  dl[k] = d;
  il[k * stride] = static_cast<int32_t>(f);
}

// Whether a pixel is on the inner side of an edge with value e (the edge owning ties where
// `own`): bitwise, not short-circuit, so the row loop below stays branch-free; NaN is outside,
// as in _raster.py.
inline bool Inside(float e, bool own) { return (e > 0.0f) | ((e == 0.0f) & own); }

// Bounding boxes at least this wide are tested a row at a time without branches (vectorised);
// narrower ones pixel by pixel, each test stopping at the first edge that fails. Measured on an
// icosphere: a row at a time, 5,120 faces take 15 % less at 256² and 23 % less at 512², while
// 81,920 faces (boxes of a few pixels) took 4 % more with every box done so (8 was the threshold
// then). Since one layer's z-buffer is updated branch-free too, 4 is as fast or faster: one
// layer, 5,120 faces at 256² 1.20 -> 1.10 ms, 81,920 at 512² 9.0 -> 8.8 ms; four layers within
// noise.
constexpr int64_t kRowSpan = 4;

// Rasterize one image: rows [row_begin, row_end) only (row bands are independent).
template <int kCount>
DIFFSHADE_CLONES void RasterBand(const float* coef, const float* zw, const int32_t* meta, int64_t num_faces,
                                  int64_t height, int64_t width, int64_t layers, int keep, int64_t row_begin,
                                  int64_t row_end, float* depth_buf, int32_t* ids) {
  ScopedFlushDenormals ftz;
  constexpr float kInf = std::numeric_limits<float>::infinity();
  thread_local std::vector<float> row;  // one row's depths (pass 1 below)
  const int64_t nf = num_faces;
  const int64_t stride = height * width;
  for (int64_t f = 0; f < nf; ++f) {
    // Structure of arrays: field k of face f is at [k * num_faces + f].
    int64_t x0 = meta[f], x1 = meta[nf + f], y0 = meta[2 * nf + f], y1 = meta[3 * nf + f];
    if (x0 > x1) continue;
    if (y0 < row_begin) y0 = row_begin;
    if (y1 >= row_end) y1 = row_end - 1;
    if (y0 > y1) continue;
    const int32_t own = meta[4 * nf + f];
    Plane pl[3];
    for (int k = 0; k < 3; ++k) {
      const float* src = coef + 3 * k * nf;
      pl[k].c0 = src[f];
      pl[k].x = Split(src[nf + f], keep, kCount);
      pl[k].y = Split(src[2 * nf + f], keep, kCount);
    }
    Depth dp;
    dp.d0 = zw[f];
    for (int k = 0; k < 3; ++k) {
      dp.dz[k] = zw[(1 + k) * nf + f];
      dp.w[k] = zw[(4 + k) * nf + f];
    }
    const bool own0 = own & 1, own1 = own & 2, own2 = own & 4;
    const int64_t span = x1 - x0 + 1;
    if (span < kRowSpan) {
      for (int64_t py = y0; py <= y1; ++py) {
        const float qy = static_cast<float>(2 * py + 1);
        for (int64_t px = x0; px <= x1; ++px) {
          const float qx = static_cast<float>(2 * px + 1);
          const float e0 = Eval<kCount>(pl[0], qx, qy);
          if (!Inside(e0, own0)) continue;
          const float e1 = Eval<kCount>(pl[1], qx, qy);
          if (!Inside(e1, own1)) continue;
          const float e2 = Eval<kCount>(pl[2], qx, qy);
          if (!Inside(e2, own2)) continue;
          float d;
          if (!DepthAt(dp, e0, e1, e2, &d)) continue;
          Insert(d, py * width + px, f, layers, stride, depth_buf, ids);
        }
      }
      continue;
    }
    if (static_cast<int64_t>(row.size()) < span) row.resize(static_cast<size_t>(span));
    float* rd = row.data();
    for (int64_t py = y0; py <= y1; ++py) {
      const float qy = static_cast<float>(2 * py + 1);
      // Pass 1, branch-free (the compiler vectorises it): every pixel of the row's span gets its
      // depth if the triangle covers it there, +inf if not. The same operations in the same
      // order as a test pixel by pixel: only which results are looked at differs.
      const int32_t q0 = static_cast<int32_t>(2 * x0 + 1), n = static_cast<int32_t>(span);
      float rp[3];
      for (int k = 0; k < 3; ++k) rp[k] = RowPart<kCount>(pl[k], qy);
      for (int32_t i = 0; i < n; ++i) {
        const float qx = static_cast<float>(q0 + 2 * i);  // (int32: SSE2 converts it 4 at a time)
        const float e0 = XPart<kCount>(pl[0], rp[0], qx);
        const float e1 = XPart<kCount>(pl[1], rp[1], qx);
        const float e2 = XPart<kCount>(pl[2], rp[2], qx);
        float d;
        const bool in_depth = DepthAt(dp, e0, e1, e2, &d);
        const bool inside = Inside(e0, own0) & Inside(e1, own1) & Inside(e2, own2) & in_depth;
        rd[i] = inside ? d : kInf;
      }
      // Pass 2: the covered pixels' fragments into their sorted lists. One layer: a z-buffer,
      // kept branch-free (vectorised) with Insert's test (a NaN or +inf depth is not below).
      if (layers == 1) {
        float* dz = depth_buf + py * width + x0;
        int32_t* iz = ids + py * width + x0;
        const int32_t fid = static_cast<int32_t>(f);
        for (int32_t i = 0; i < n; ++i) {
          const bool nearer = rd[i] < dz[i];
          dz[i] = nearer ? rd[i] : dz[i];
          iz[i] = nearer ? fid : iz[i];
        }
        continue;
      }
      for (int64_t i = 0; i < span; ++i) Insert(rd[i], py * width + x0 + i, f, layers, stride, depth_buf, ids);
    }
  }
}

// NDC plane (c, ax, ay) scaled by W * H into pixel units (_raster.py::_to_pixel_units).
// The bounding box's margin around a triangle in front of the near plane (_raster.py BOX_MARGIN).
constexpr float kBoxMargin = 1.0f / 64;

inline void ToPixelUnits(float c, float ax, float ay, int64_t height, int64_t width, float* out) {
  const float wh = static_cast<float>(width * height);
  out[0] = Mul((c - ax) + ay, wh);
  out[1] = Mul(ax, static_cast<float>(height));
  out[2] = -Mul(ay, static_cast<float>(width));
}

// The pixel bounding box of a triangle's part in front of the near plane (z >= -w), and its
// ownership bits, into meta; an empty box (x0 > x1) for a triangle that draws nothing.
void BoundingBox(const float* x, const float* y, const float* z, const float* w, bool bad, float det,
                 int32_t own, int64_t height, int64_t width, int32_t* meta, int64_t nf, int64_t f) {
  const float big = 1e7f;
  float xmin = big, xmax = -big, ymin = big, ymax = -big;
  bool finite = !bad, any_inside = false;
  float dist[3];
  for (int k = 0; k < 3; ++k) {
    finite = finite && std::isfinite(x[k]) && std::isfinite(y[k]) && std::isfinite(z[k]) && std::isfinite(w[k]);
    dist[k] = z[k] + w[k];
  }
  auto add = [&](float px, float py, float pw) {
    if (!(pw > 0)) return;
    const float nx = std::min(std::max(px / pw, -big), big), ny = std::min(std::max(py / pw, -big), big);
    xmin = std::min(xmin, nx); xmax = std::max(xmax, nx);
    ymin = std::min(ymin, ny); ymax = std::max(ymax, ny);
  };
  for (int k = 0; k < 3; ++k) {
    if (dist[k] >= 0) { any_inside = true; add(x[k], y[k], w[k]); }
  }
  for (int k = 0; k < 3; ++k) {
    const int a = k, b = (k + 1) % 3;
    if ((dist[a] >= 0) != (dist[b] >= 0)) {
      const float t = dist[a] / (dist[a] - dist[b]);
      add(x[a] + t * (x[b] - x[a]), y[a] + t * (y[b] - y[a]), w[a] + t * (w[b] - w[a]));
    }
  }
  const float hw = static_cast<float>(width) / 2, hh = static_cast<float>(height) / 2;
  // margin: kBoxMargin pixels for a triangle wholly in front of the near plane, else one pixel
  const float pad = (dist[0] >= 0 && dist[1] >= 0 && dist[2] >= 0) ? kBoxMargin : 1.0f;
  float fx0 = std::floor((xmin + 1) * hw - 0.5f - pad), fx1 = std::ceil((xmax + 1) * hw - 0.5f + pad);
  float fy0 = std::floor((1 - ymax) * hh - 0.5f - pad), fy1 = std::ceil((1 - ymin) * hh - 0.5f + pad);
  int32_t x0 = static_cast<int32_t>(std::min(std::max(fx0, 0.0f), static_cast<float>(width)));
  int32_t x1 = static_cast<int32_t>(std::min(std::max(fx1, -1.0f), static_cast<float>(width - 1)));
  int32_t y0 = static_cast<int32_t>(std::min(std::max(fy0, 0.0f), static_cast<float>(height)));
  int32_t y1 = static_cast<int32_t>(std::min(std::max(fy1, -1.0f), static_cast<float>(height - 1)));
  const bool valid = any_inside && det != 0 && finite && y0 <= y1 && xmin <= xmax;
  if (!valid) { x0 = 1; x1 = 0; }
  meta[f] = x0; meta[nf + f] = x1; meta[2 * nf + f] = y0; meta[3 * nf + f] = y1; meta[4 * nf + f] = own;
}

// Triangle set-up: the same operations as diffshade/_raster.py::_setup (canonical vertex order,
// exact products, conservative near-clipped bounding box), written to structure-of-arrays, the
// planes and depth weights by the vertices' canonical rank.
// Faces go in blocks of kBlock: their vertices gathered first, then each quantity for the whole
// block in a loop of straight-line arithmetic (selects, no branches), which the compiler
// vectorises; the bounding box after, face by face.
constexpr int64_t kBlock = 64;

// cull: the sign det must have for the triangle to be drawn (1: counter-clockwise on the screen,
// the front; -1: clockwise; 0: either), _raster.py's `cull`.
void Setup(const float* clip, const int32_t* faces, int64_t num_verts, int64_t nf, int64_t f_begin,
           int64_t f_end, int64_t height, int64_t width, int32_t cull, float* coef, float* zw,
           int32_t* meta) {
  ScopedFlushDenormals ftz;
  float X[3][kBlock], Y[3][kBlock], Z[3][kBlock], W[3][kBlock], minor[3][kBlock], nat[3][kBlock];
  float det[kBlock], d0[kBlock];
  int32_t VI[3][kBlock], rank[3][kBlock], of_rank[3][kBlock];
  bool bad[kBlock];
  for (int64_t f0 = f_begin; f0 < f_end; f0 += kBlock) {
    const int64_t n = std::min(kBlock, f_end - f0);
    for (int64_t j = 0; j < n; ++j) {
      bad[j] = false;
      for (int k = 0; k < 3; ++k) {
        int32_t v = faces[3 * (f0 + j) + k];
        if (v < 0 || v >= num_verts) { bad[j] = true; v = 0; }
        VI[k][j] = v;
        const float* c = clip + 4 * static_cast<int64_t>(v);
        X[k][j] = c[0]; Y[k][j] = c[1]; Z[k][j] = c[2]; W[k][j] = c[3];
      }
    }
    // Whether vertex a comes before vertex b of face j in the canonical order (_raster.py's
    // _before): lexicographic in (x, y, w, z), then by vertex index.
    auto before = [&](int a, int b, int64_t j) {
      bool lt = VI[a][j] < VI[b][j];
      const float(*qs[4])[kBlock] = {Z, W, Y, X};  // (reversed: the last compared decides first)
      for (int c = 0; c < 4; ++c) {
        const float va = qs[c][a][j], vb = qs[c][b][j];
        lt = (va < vb) | ((va == vb) & lt);
      }
      return lt;
    };
    // each vertex's rank in that order, and the vertex of each rank: the planes (plane k
    // opposite vertex k) and the depth weights are stored by rank (_raster.py::_setup)
    // (_raster.py::_ranks: the identity where the three comparisons do not order the vertices)
    for (int64_t j = 0; j < n; ++j) {
      const int b01 = before(0, 1, j), b02 = before(0, 2, j), b12 = before(1, 2, j);
      int r[3] = {(1 - b01) + (1 - b02), b01 + (1 - b12), b02 + b12};
      if (r[0] == r[1] || r[0] == r[2] || r[1] == r[2]) { r[0] = 0; r[1] = 1; r[2] = 2; }
      for (int k = 0; k < 3; ++k) {
        rank[k][j] = r[k];
        of_rank[r[k]][j] = k;
      }
    }
    // minors of the (x, y) columns in canonical order, and in natural order
    for (int i = 0; i < 3; ++i) {
      const int a = (i + 1) % 3, b = (i + 2) % 3;
      for (int64_t j = 0; j < n; ++j) {
        const bool sw = before(b, a, j);
        const float xa = sw ? X[b][j] : X[a][j], ya = sw ? Y[b][j] : Y[a][j];
        const float xb = sw ? X[a][j] : X[b][j], yb = sw ? Y[a][j] : Y[b][j];
        const float m = Mul(xa, yb) - Mul(xb, ya);
        minor[i][j] = m;
        nat[i][j] = sw ? -m : m;
      }
    }
    for (int64_t j = 0; j < n; ++j) {
      det[j] = (Mul(W[0][j], nat[0][j]) + Mul(W[1][j], nat[1][j])) + Mul(W[2][j], nat[2][j]);
    }
    // the edge functions (NDC) and in pixel units, with the tie rule's ownership bits
    for (int i = 0; i < 3; ++i) {
      const int a = (i + 1) % 3, b = (i + 2) % 3;
      for (int64_t j = 0; j < n; ++j) {
        const bool sw = before(b, a, j);
        const float sdet = det[j] > 0 ? 1.0f : -1.0f;
        const float s = sw ? -sdet : sdet;
        const float xa = sw ? X[b][j] : X[a][j], ya = sw ? Y[b][j] : Y[a][j], wa = sw ? W[b][j] : W[a][j];
        const float xb = sw ? X[a][j] : X[b][j], yb = sw ? Y[a][j] : Y[b][j], wb = sw ? W[a][j] : W[b][j];
        const float cc = s * minor[i][j];
        const float ax = s * (Mul(wb, ya) - Mul(wa, yb));
        const float ay = s * (Mul(xb, wa) - Mul(xa, wb));
        float cf[3];
        ToPixelUnits(cc, ax, ay, height, width, cf);
        for (int k = 0; k < 3; ++k) coef[(3 * rank[i][j] + k) * nf + f0 + j] = cf[k];
      }
    }
    // the depth weights (Depth), in loops over the block that vectorise
    for (int64_t j = 0; j < n; ++j) {
      const int p0 = of_rank[0][j], p1 = of_rank[1][j], p2 = of_rank[2][j];
      const float zs = (Z[p0][j] + Z[p1][j]) + Z[p2][j], ws = (W[p0][j] + W[p1][j]) + W[p2][j];
      const float d = zs / (ws > 0 ? ws : 1.0f);
      const float lo = d < -1.0f ? -1.0f : d;
      d0[j] = ws > 0 ? (lo > 1.0f ? 1.0f : lo) : 0.0f;
      zw[f0 + j] = d0[j];
    }
    for (int k = 0; k < 3; ++k) {
      for (int64_t j = 0; j < n; ++j) {
        const int v = of_rank[k][j];
        zw[(1 + k) * nf + f0 + j] = Trunc(Z[v][j] - Mul(d0[j], W[v][j]), 12);
        zw[(4 + k) * nf + f0 + j] = Trunc(W[v][j], 12);
      }
    }
    for (int64_t j = 0; j < n; ++j) {
      const int64_t f = f0 + j;
      int32_t own = 0;
      for (int i = 0; i < 3; ++i) {
        // Tie rule (see _raster.py): the centre is displaced by (eps, eps^2) in pixel units.
        const float cx = coef[(3 * i + 1) * nf + f], cy = coef[(3 * i + 2) * nf + f];
        if (cx > 0 || (cx == 0 && cy > 0)) own |= 1 << i;
      }
      float x[3], y[3], z[3], w[3];
      for (int k = 0; k < 3; ++k) { x[k] = X[k][j]; y[k] = Y[k][j]; z[k] = Z[k][j]; w[k] = W[k][j]; }
      const bool culled = (cull > 0 && !(det[j] > 0)) || (cull < 0 && !(det[j] < 0));
      BoundingBox(x, y, z, w, bad[j] || culled, det[j], own, height, width, meta, nf, f);
    }
  }
}

ffi::Error RasterImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> clip, ffi::Buffer<ffi::S32> faces,
                      ffi::ResultBuffer<ffi::S32> out, int32_t cull) {
  // Shapes: clip [..., V, 4], faces [..., F, 3], out [..., K, H, W].
  // Leading dimensions are a batch (vmap with broadcast_all).
  auto odims = out->dimensions();
  auto cdims = clip.dimensions();
  auto fdims = faces.dimensions();
  if (odims.size() < 3 || cdims.size() < 2 || fdims.size() < 2) {
    return ffi::Error::InvalidArgument("diffshade_raster: bad ranks");
  }
  const int64_t width = odims[odims.size() - 1];
  const int64_t height = odims[odims.size() - 2];
  const int64_t layers = odims[odims.size() - 3];
  const int64_t num_verts = cdims[cdims.size() - 2];
  const int64_t num_faces = fdims[fdims.size() - 2];
  int keep = 0, count = 0;
  PiecePlan(height, width, &keep, &count);
  if (count < 2 || count > 3) {
    return ffi::Error::InvalidArgument("diffshade_raster: image side out of range");
  }
  // Scratch kept per calling thread between calls: fresh buffers each call were page-faulted
  // in and zeroed every time (7 % of a call at 81,920 faces); every element is written before
  // it is read.
  thread_local std::vector<float> coef, zw, depth;
  thread_local std::vector<int32_t> meta;
  coef.resize(static_cast<size_t>(9 * num_faces));
  zw.resize(static_cast<size_t>(7 * num_faces));
  meta.resize(static_cast<size_t>(5 * num_faces));
  int64_t batch = 1;
  for (size_t i = 0; i + 3 < odims.size(); ++i) batch *= odims[i];
  const int64_t npix = height * width;
  int32_t* ids_all = out->typed_data();
  depth.resize(static_cast<size_t>(npix * layers));
  unsigned hw = std::thread::hardware_concurrency();
  int64_t nthreads = hw == 0 ? 1 : static_cast<int64_t>(hw);
  if (nthreads > 8) nthreads = 8;
  if (nthreads > height) nthreads = height;
  if (num_faces * 1.0 * npix < 2.0e6) nthreads = 1;  // not worth a thread for tiny jobs
  auto band = count == 2 ? RasterBand<2> : RasterBand<3>;
  for (int64_t b = 0; b < batch; ++b) {
    int32_t* ids = ids_all + b * layers * npix;
    std::fill(depth.begin(), depth.end(), std::numeric_limits<float>::infinity());
    std::fill(ids, ids + layers * npix, -1);
    const float* bclip = clip.typed_data() + b * num_verts * 4;
    const int32_t* bfaces = faces.typed_data() + b * num_faces * 3;
    float* pc = coef.data();
    float* pz = zw.data();
    int32_t* pm = meta.data();
    float* pd = depth.data();  // (the threads below have thread_local scratch of their own)
    // Set-up over face ranges, then rasterization over row bands, on the same threads.
    diffshade::ParallelFor(pool, nthreads, [&](int64_t t) {
      const int64_t f0 = num_faces * t / nthreads, f1 = num_faces * (t + 1) / nthreads;
      Setup(bclip, bfaces, num_verts, num_faces, f0, f1, height, width, cull, pc, pz, pm);
    });
    diffshade::ParallelFor(pool, nthreads, [&](int64_t t) {
      const int64_t r0 = height * t / nthreads, r1 = height * (t + 1) / nthreads;
      band(pc, pz, pm, num_faces, height, width, layers, keep, r0, r1, pd, ids);
    });
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffshadeRaster, RasterImpl,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()  // XLA's intra-op threads
                                  .Arg<ffi::Buffer<ffi::F32>>()  // clip
                                  .Arg<ffi::Buffer<ffi::S32>>()  // faces
                                  .Ret<ffi::Buffer<ffi::S32>>()  // ids
                                  .Attr<int32_t>("cull"));  // 1 back, -1 front, 0 none
