// diffshade native visibility kernel (CPU), registered with XLA through jax.ffi.
//
// It implements the same set-up and per-pixel test as the pure-JAX tiled rasterizer
// (diffshade/_raster.py): a pixel (x, y) is covered by triangle f when, for each edge i,
//     E'_i = (C_i + x * Ax_i) + y * Ay_i  >  0,  or  == 0 and the edge owns ties,
// and the interpolated NDC depth d = Z / W with Z = (Zc + x Zx) + y Zy, W = (Wc + x Wx) + y Wy
// satisfies -W <= Z <= W. Fragments are kept per pixel as the K nearest by (depth, triangle id).
// Compiled with -ffp-contract=off so that the arithmetic is the plain IEEE sequence above. XLA
// may contract a*b + c into a fused multiply-add, so the two paths can differ in the last bit
// of an edge function; only pixels exactly on an edge (E = 0 in exact arithmetic) can then be
// assigned differently. The tests compare the two everywhere else.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// Rasterize one image: rows [row_begin, row_end) only (row bands are independent).
void RasterBand(const float* xs, const float* ys, const float* coef, const float* zw,
                const int32_t* meta, int64_t num_faces, int64_t height, int64_t width,
                int64_t layers, int64_t row_begin, int64_t row_end, float* depth_buf,
                int32_t* ids) {
  for (int64_t f = 0; f < num_faces; ++f) {
    // Structure of arrays: field k of face f is at [k * num_faces + f].
    const int64_t nf = num_faces;
    int64_t x0 = meta[f], x1 = meta[nf + f], y0 = meta[2 * nf + f], y1 = meta[3 * nf + f];
    if (x0 > x1) continue;
    if (y0 < row_begin) y0 = row_begin;
    if (y1 >= row_end) y1 = row_end - 1;
    if (y0 > y1) continue;
    const int32_t own = meta[4 * nf + f];
    float c[9], z[6];
    for (int k = 0; k < 9; ++k) c[k] = coef[k * nf + f];
    for (int k = 0; k < 6; ++k) z[k] = zw[k * nf + f];
    const bool own0 = own & 1, own1 = own & 2, own2 = own & 4;
    for (int64_t py = y0; py <= y1; ++py) {
      const float y = ys[py];
      for (int64_t px = x0; px <= x1; ++px) {
        const float x = xs[px];
        const float e0 = (c[0] + x * c[1]) + y * c[2];  // same operand order as _raster.py
        if (e0 < 0.0f || (e0 == 0.0f && !own0)) continue;
        const float e1 = (c[3] + x * c[4]) + y * c[5];
        if (e1 < 0.0f || (e1 == 0.0f && !own1)) continue;
        const float e2 = (c[6] + x * c[7]) + y * c[8];
        if (e2 < 0.0f || (e2 == 0.0f && !own2)) continue;
        const float zz = (z[0] + x * z[1]) + y * z[2];
        const float ww = (z[3] + x * z[4]) + y * z[5];
        if (!(zz >= -ww && zz <= ww)) continue;
        const float d = zz / ww;
        const int64_t pix = py * width + px;
        // Insert into the per-pixel sorted list of K (depth, id); ids arrive in increasing
        // order, so equal depths keep the earlier (smaller) id first.
        float* dl = depth_buf + pix * layers;
        int32_t* il = ids + pix;  // stride height * width between layers
        const int64_t stride = height * width;
        if (!(d < dl[layers - 1])) continue;
        int64_t k = layers - 1;
        while (k > 0 && dl[k - 1] > d) {
          dl[k] = dl[k - 1];
          il[k * stride] = il[(k - 1) * stride];
          --k;
        }
        dl[k] = d;
        il[k * stride] = static_cast<int32_t>(f);
      }
    }
  }
}


// Triangle set-up: the same formulas as diffshade/_raster.py::_setup (canonical edge order,
// conservative near-clipped bounding box), written to structure-of-arrays buffers.
void Setup(const float* clip, const int32_t* faces, int64_t num_verts, int64_t nf, int64_t height,
           int64_t width, float* coef, float* zw, int32_t* meta) {
  for (int64_t f = 0; f < nf; ++f) {
    int32_t vi[3];
    float x[3], y[3], z[3], w[3];
    bool bad = false;
    for (int k = 0; k < 3; ++k) {
      vi[k] = faces[3 * f + k];
      if (vi[k] < 0 || vi[k] >= num_verts) { bad = true; vi[k] = 0; }
      const float* c = clip + 4 * static_cast<int64_t>(vi[k]);
      x[k] = c[0]; y[k] = c[1]; z[k] = c[2]; w[k] = c[3];
    }
    const float det = (x[0] * (y[1] * w[2] - y[2] * w[1]) - y[0] * (x[1] * w[2] - x[2] * w[1])) +
                      w[0] * (x[1] * y[2] - x[2] * y[1]);
    const float sdet = det > 0 ? 1.0f : -1.0f;
    float cf[9];
    int32_t own = 0;
    for (int i = 0; i < 3; ++i) {
      int a = (i + 1) % 3, b = (i + 2) % 3;
      const float s = vi[a] > vi[b] ? -sdet : sdet;
      if (vi[a] > vi[b]) std::swap(a, b);
      cf[3 * i + 0] = s * (x[a] * y[b] - x[b] * y[a]);
      cf[3 * i + 1] = s * (w[b] * y[a] - w[a] * y[b]);
      cf[3 * i + 2] = s * (x[b] * w[a] - x[a] * w[b]);
      // Tie rule (see _raster.py): the centre is displaced by (eps, eps^2).
      if (cf[3 * i + 1] > 0 || (cf[3 * i + 1] == 0 && cf[3 * i + 2] > 0)) own |= 1 << i;
    }
    for (int j = 0; j < 3; ++j) {
      zw[j * nf + f] = (cf[j] * z[0] + cf[3 + j] * z[1]) + cf[6 + j] * z[2];
      zw[(3 + j) * nf + f] = (cf[j] * w[0] + cf[3 + j] * w[1]) + cf[6 + j] * w[2];
    }
    for (int k = 0; k < 9; ++k) coef[k * nf + f] = cf[k];
    // Bounding box of the part in front of the near plane (z >= -w).
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
    float fx0 = std::floor((xmin + 1) * hw - 0.5f) - 1, fx1 = std::ceil((xmax + 1) * hw - 0.5f) + 1;
    float fy0 = std::floor((1 - ymax) * hh - 0.5f) - 1, fy1 = std::ceil((1 - ymin) * hh - 0.5f) + 1;
    int32_t x0 = static_cast<int32_t>(std::min(std::max(fx0, 0.0f), static_cast<float>(width)));
    int32_t x1 = static_cast<int32_t>(std::min(std::max(fx1, -1.0f), static_cast<float>(width - 1)));
    int32_t y0 = static_cast<int32_t>(std::min(std::max(fy0, 0.0f), static_cast<float>(height)));
    int32_t y1 = static_cast<int32_t>(std::min(std::max(fy1, -1.0f), static_cast<float>(height - 1)));
    const bool valid = any_inside && det != 0 && finite && y0 <= y1 && xmin <= xmax;
    if (!valid) { x0 = 1; x1 = 0; }
    meta[f] = x0; meta[nf + f] = x1; meta[2 * nf + f] = y0; meta[3 * nf + f] = y1; meta[4 * nf + f] = own;
  }
}

ffi::Error RasterImpl(ffi::Buffer<ffi::F32> xs, ffi::Buffer<ffi::F32> ys,
                      ffi::Buffer<ffi::F32> clip, ffi::Buffer<ffi::S32> faces,
                      ffi::ResultBuffer<ffi::S32> out) {
  // Shapes: xs [..., W], ys [..., H], clip [..., V, 4], faces [..., F, 3], out [..., K, H, W].
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
  std::vector<float> coef(static_cast<size_t>(9 * num_faces)), zw(static_cast<size_t>(6 * num_faces));
  std::vector<int32_t> meta(static_cast<size_t>(5 * num_faces));
  int64_t batch = 1;
  for (size_t i = 0; i + 3 < odims.size(); ++i) batch *= odims[i];
  const int64_t npix = height * width;
  int32_t* ids_all = out->typed_data();
  std::vector<float> depth(static_cast<size_t>(npix * layers));
  unsigned hw = std::thread::hardware_concurrency();
  int64_t nthreads = hw == 0 ? 1 : static_cast<int64_t>(hw);
  if (nthreads > 8) nthreads = 8;
  if (nthreads > height) nthreads = height;
  if (num_faces * 1.0 * npix < 2.0e6) nthreads = 1;  // not worth a thread for tiny jobs
  for (int64_t b = 0; b < batch; ++b) {
    int32_t* ids = ids_all + b * layers * npix;
    std::fill(depth.begin(), depth.end(), std::numeric_limits<float>::infinity());
    std::fill(ids, ids + layers * npix, -1);
    const float* bx = xs.typed_data() + b * width;
    const float* by = ys.typed_data() + b * height;
    Setup(clip.typed_data() + b * num_verts * 4, faces.typed_data() + b * num_faces * 3, num_verts,
          num_faces, height, width, coef.data(), zw.data(), meta.data());
    const float* bc = coef.data();
    const float* bz = zw.data();
    const int32_t* bm = meta.data();
    if (nthreads <= 1) {
      RasterBand(bx, by, bc, bz, bm, num_faces, height, width, layers, 0, height, depth.data(),
                 ids);
    } else {
      std::vector<std::thread> pool;
      for (int64_t t = 0; t < nthreads; ++t) {
        const int64_t r0 = height * t / nthreads, r1 = height * (t + 1) / nthreads;
        pool.emplace_back(RasterBand, bx, by, bc, bz, bm, num_faces, height, width, layers, r0,
                          r1, depth.data(), ids);
      }
      for (auto& th : pool) th.join();
    }
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffshadeRaster, RasterImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()  // xs
                                  .Arg<ffi::Buffer<ffi::F32>>()  // ys
                                  .Arg<ffi::Buffer<ffi::F32>>()  // clip
                                  .Arg<ffi::Buffer<ffi::S32>>()  // faces
                                  .Ret<ffi::Buffer<ffi::S32>>());  // ids
