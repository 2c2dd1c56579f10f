// diffshade: exp, log and x^m over W float lanes in GCC's vector extensions (see shade.cc,
// MapLanes). Included once per width, in a namespace that defines W and
// the vector types F (W floats) and I (W int32s) before it.
// (No include guard: it is meant to be included more than once.)
[[gnu::always_inline]] inline F Splat(float a) { return F{} + a; }

// e^x for x in [-87.3, 88.3] (clamped there: the callers need no more; 2^n stays a normal float).
[[gnu::always_inline]] inline F Exp(F x) {
  x = x < Splat(-87.3f) ? Splat(-87.3f) : x;  // std::max(x, -87.3f)
  x = Splat(88.3f) < x ? Splat(88.3f) : x;    // std::min(x, 88.3f)
  const F v = x * 1.44269504088896341f + 0.5f;
  I n = __builtin_convertvector(v, I);
  n = n + (__builtin_convertvector(n, F) > v);  // (a true comparison is -1)
  const F fn = __builtin_convertvector(n, F);
  F r = x - fn * 0.693359375f;
  r = r - fn * -2.12194440e-4f;
  const F z = r * r;
  F y = Splat(1.9875691500e-4f);
  y = y * r + 1.3981999507e-3f;
  y = y * r + 8.3334519073e-3f;
  y = y * r + 4.1665795894e-2f;
  y = y * r + 1.6666665459e-1f;
  y = y * r + 5.0000001201e-1f;
  y = y * z + r + 1.0f;
  return y * reinterpret_cast<F>((n + 127) << 23);
}

// log x for positive normal floats x.
[[gnu::always_inline]] inline F Log(F x) {
  const I i = reinterpret_cast<I>(x);
  I e = ((i >> 23) & 0xff) - 126;
  F m = reinterpret_cast<F>((i & 0x007fffff) | 0x3f000000);
  const I small = m < 0.707106781186547524f;
  e = e + small;
  m = (small ? m + m : m) - 1.0f;
  const F z = m * m;
  F y = Splat(7.0376836292e-2f);
  y = y * m - 1.1514610310e-1f;
  y = y * m + 1.1676998740e-1f;
  y = y * m - 1.2420140846e-1f;
  y = y * m + 1.4249322787e-1f;
  y = y * m - 1.6668057665e-1f;
  y = y * m + 2.0000714765e-1f;
  y = y * m - 2.4999993993e-1f;
  y = y * m + 3.3333331174e-1f;
  const F fe = __builtin_convertvector(e, F);
  y = y * m * z;
  y = y + -2.12194440e-4f * fe;
  y = y - 0.5f * z;
  return (m + y) + 0.693359375f * fe;
}

// x^m with 0^m = 0 and 0 where m log x is below the log of the smallest normal float
// (_shade.safe_pow): branch-free.
[[gnu::always_inline]] inline F SafePow(F x, F m) {
  const float kFloor = -87.3365447505531f;  // log(FLT_MIN)
  const I pos = x >= std::numeric_limits<float>::min();  // (flushed denormals: as XLA's 0)
  const F t = m * Log(pos ? x : Splat(1.0f));
  return (pos & (t > kFloor)) ? Exp(t) : Splat(0.0f);
}

// Whether a lane of x is a positive normal float (SafePow's base that is not taken as 0).
[[gnu::always_inline]] inline bool AnyNormal(F x) {
  const I pos = x >= std::numeric_limits<float>::min();
  int any = 0;
  for (int l = 0; l < W; ++l) any |= pos[l];
  return any != 0;
}

// out[q] = op(x[q]) for q < m (MapLanes).
[[gnu::always_inline]] inline void Map(int op, const float* x, const float* e, int e_step, float* out, int m) {
  const F e0 = op == kPow ? Splat(e[0]) : F{};
  for (int q = 0; q < m; q += W) {
    F a, r;
    std::memcpy(&a, x + q, sizeof a);
    if (op == kExp) {
      r = Exp(a);
    } else if (op == kLog) {
      r = Log(a);
    } else if (AnyNormal(a)) {
      F b = e0;
      if (e_step) std::memcpy(&b, e + q, sizeof b);
      r = SafePow(a, b);
    } else {  // (SafePow's value where no lane has a positive normal base: the specular term's
      r = F{};  // off-highlight pixels, most of an image, skip the log and exp)
    }
    std::memcpy(out + q, &r, sizeof r);
  }
}
