// diffshade native vertex normals (CPU), registered with XLA through jax.ffi.
//
// The area-weighted vertex normals of diffshade/_mesh.py::Mesh.vertex_normals (docs/model.md §4):
// per vertex the sum of its faces' cross products (v1 - v0) x (v2 - v0), normalised, and the zero
// vector where that sum is within cancel * FLT_EPSILON of the sum of its faces' |e1||e2| (the
// faces cancel: the sum is rounding). The same function of the same float32 inputs wherever it
// runs: inside a jitted render, a fit's program or an eager call, whatever XLA fuses around it
// (compiled with -ffp-contract=off), so a fit's host-side normals and a render's are the same bits.

#include <cfloat>
#include <cmath>
#include <cstdint>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

void Normals(const float* v, const int32_t* f, int64_t nv, int64_t nf, float cancel, float* out) {
  thread_local std::vector<float> acc;  // per vertex: the sum (x, y, z) and the bound
  acc.assign(static_cast<size_t>(4 * nv), 0.0f);
  for (int64_t t = 0; t < nf; ++t) {
    const int32_t a = f[3 * t], b = f[3 * t + 1], c = f[3 * t + 2];
    if (a < 0 || b < 0 || c < 0 || a >= nv || b >= nv || c >= nv) continue;  // (as XLA drops them)
    const float* p0 = v + 3 * static_cast<int64_t>(a);
    const float* p1 = v + 3 * static_cast<int64_t>(b);
    const float* p2 = v + 3 * static_cast<int64_t>(c);
    const float e1[3] = {p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]};
    const float e2[3] = {p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]};
    const float n[4] = {
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
        std::sqrt(((e1[0] * e1[0] + e1[1] * e1[1]) + e1[2] * e1[2]) * ((e2[0] * e2[0] + e2[1] * e2[1]) + e2[2] * e2[2])),
    };
    for (const int32_t k : {a, b, c}) {
      float* s = acc.data() + 4 * static_cast<int64_t>(k);
      for (int i = 0; i < 4; ++i) s[i] += n[i];
    }
  }
  for (int64_t k = 0; k < nv; ++k) {
    const float* s = acc.data() + 4 * k;
    const float sq = (s[0] * s[0] + s[1] * s[1]) + s[2] * s[2];
    const float tol = cancel * FLT_EPSILON * s[3];
    float* o = out + 3 * k;
    if (sq > tol * tol && sq > 0.0f) {
      const float len = std::sqrt(sq);
      for (int i = 0; i < 3; ++i) o[i] = s[i] / len;
    } else {
      o[0] = o[1] = o[2] = 0.0f;
    }
  }
}

ffi::Error NormalsImpl(ffi::Buffer<ffi::F32> vertices, ffi::Buffer<ffi::S32> faces, ffi::ResultBuffer<ffi::F32> out,
                       float cancel) {
  // Shapes: vertices [..., V, 3], faces [..., F, 3], out [..., V, 3]; the leading dimensions a
  // batch (vmap with broadcast_all).
  auto vd = vertices.dimensions();
  auto fd = faces.dimensions();
  if (vd.size() < 2 || fd.size() < 2 || vd.back() != 3 || fd.back() != 3) {
    return ffi::Error::InvalidArgument("diffshade_normals: vertices and faces must be [..., N, 3]");
  }
  const int64_t nv = vd[vd.size() - 2], nf = fd[fd.size() - 2];
  int64_t batch = 1;
  for (size_t i = 0; i + 2 < vd.size(); ++i) batch *= vd[i];
  for (int64_t b = 0; b < batch; ++b) {
    Normals(vertices.typed_data() + b * nv * 3, faces.typed_data() + b * nf * 3, nv, nf, cancel,
            out->typed_data() + b * nv * 3);
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffshadeNormals, NormalsImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()  // vertices
                                  .Arg<ffi::Buffer<ffi::S32>>()  // faces
                                  .Ret<ffi::Buffer<ffi::F32>>()  // normals
                                  .Attr<float>("cancel"));
