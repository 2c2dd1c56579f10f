// A supernodal multifrontal Cholesky factorisation of a sparse symmetric positive definite matrix,
// and its solves (fitting/_sparse.py's Factor). The dense work of each supernode goes through
// BLAS and LAPACK: their function pointers are handed in by the caller (SciPy's, from
// scipy.linalg.cython_blas / cython_lapack), so nothing here links against a BLAS of its own.
//
// The steps (Liu, "The multifrontal method for sparse matrix solution", SIAM Review 1992; Davis,
// "Direct Methods for Sparse Linear Systems", 2006, for the elimination tree and the counts):
//   1. the caller's fill-reducing ordering (METIS's nested dissection) is composed with a postorder
//      of the elimination tree, so that every supernode is a range of consecutive columns and every
//      subtree too;
//   2. column counts from the row subtrees, fundamental supernodes, then relaxed amalgamation
//      (a child merged into its parent where few explicit zeros result, as CHOLMOD's defaults);
//      steps 1-2 are the symbolic analysis, made once per pattern and shared (read-only) by the
//      factorisations of every matrix whose entries lie within it;
//   3. for each supernode in postorder, its frontal matrix: the matrix's columns and the children's
//      update matrices added in (extend-add), then POTRF on the diagonal block, TRSM below it and
//      SYRK for the update matrix the parent takes;
//   4. the solves, forward and backward over the supernodes: by hand for one column and for small
//      supernodes, TRSM/GEMM for several columns.
// A pivot that is not positive (POTRF's info) fails the factorisation, and the caller falls back.
#include <dlfcn.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <new>
#include <string>
#include <type_traits>
#include <vector>

namespace {

using i64 = int64_t;

typedef void (*dgemm_t)(const char*, const char*, const int*, const int*, const int*, const double*,
                        const double*, const int*, const double*, const int*, const double*, double*,
                        const int*);
typedef void (*dsyrk_t)(const char*, const char*, const int*, const int*, const double*, const double*,
                        const int*, const double*, double*, const int*);
typedef void (*dtrsm_t)(const char*, const char*, const char*, const char*, const int*, const int*,
                        const double*, const double*, const int*, double*, const int*);
typedef void (*dpotrf_t)(const char*, const int*, double*, const int*, int*);

struct Blas {
  dgemm_t gemm = nullptr;
  dsyrk_t syrk = nullptr;
  dtrsm_t trsm = nullptr;
  dpotrf_t potrf = nullptr;
};
Blas blas;

// OpenBLAS's thread count, held at one while any factorisation or solve runs: the caller runs
// several in threads of its own, and OpenBLAS's workers, spinning between calls, would take the
// cores from them (a 55k-scalar channel's factorisation, three in threads on two cores: 0.23 s
// against 0.10 s). Found beside the BLAS handed in; absent (another BLAS), nothing is done.
typedef void (*set_threads_t)(int);
typedef int (*get_threads_t)();
set_threads_t set_threads = nullptr;
get_threads_t get_threads = nullptr;
std::mutex threads_mutex;
int threads_users = 0, threads_before = 0;

void FindThreadControl(void* fn) {
  Dl_info info;
  if (!dladdr(fn, &info) || !info.dli_fname) return;
  void* lib = dlopen(info.dli_fname, RTLD_LAZY | RTLD_NOLOAD);
  if (!lib) return;
  for (const char* prefix : {"scipy_openblas", "openblas"}) {
    const std::string set = std::string(prefix) + "_set_num_threads", get = std::string(prefix) + "_get_num_threads";
    auto s = reinterpret_cast<set_threads_t>(dlsym(lib, set.c_str()));
    auto g = reinterpret_cast<get_threads_t>(dlsym(lib, get.c_str()));
    if (s && g) {
      set_threads = s;
      get_threads = g;
      return;
    }
  }
}

struct OneBlasThread {
  OneBlasThread() {
    if (!set_threads) return;
    std::lock_guard<std::mutex> hold(threads_mutex);
    if (threads_users++ == 0) {
      threads_before = get_threads();
      if (threads_before != 1) set_threads(1);
    }
  }
  ~OneBlasThread() {
    if (!set_threads) return;
    std::lock_guard<std::mutex> hold(threads_mutex);
    if (--threads_users == 0 && threads_before != 1) set_threads(threads_before);
  }
};

// one column, and supernodes whose block times the columns solved is below this, are solved by
// hand, the rest by BLAS (a 55k-scalar channel: one column by hand 9 against 15 ms through BLAS;
// 32 columns through BLAS 34 against 81 ms by hand)
const i64 kBlasSolve = 1024;

// A supernode: columns [first, first + ncols) of the permuted matrix; its front's rows are those
// columns, then `below` (sorted, all past the last column). L's block is rows × ncols, column-major.
struct Super {
  i64 first = 0, ncols = 0;
  i64 below_at = 0, nbelow = 0;  // its rows below, in Factor::rows
  i64 lx_at = 0;                 // its block, in Factor::lx
  i64 parent = -1;
  i64 nchildren = 0;
  i64 rows() const { return ncols + nbelow; }
};

// The symbolic analysis: the ordering, the supernodes and their rows. Read-only once made, so
// that the factorisations of every matrix of its pattern (or a part of it) share one.
struct Symbolic {
  i64 n = 0;
  std::vector<i64> perm;  // new index -> the caller's index
  std::vector<Super> supers;
  std::vector<i64> rows;  // every supernode's rows below
  i64 lx_size = 0;        // L's stored entries
  i64 max_below = 0;
};

struct Factor {
  std::shared_ptr<const Symbolic> sym;
  std::unique_ptr<double[]> lx;  // every supernode's block, at its lx_at
};

// The caller's matrix M (CSC, both triangles) seen in an ordering: column k of P M Pᵀ is M's
// column perm[k], its rows relabelled by inv (perm's inverse). Nothing is copied.
struct Permuted {
  const i64 *colptr, *rowind;
  const double* val;
  std::vector<i64> perm, inv;
  Permuted(i64 n, const i64* cp, const i64* ri, const double* v, const i64* order)
      : colptr(cp), rowind(ri), val(v), perm(order, order + n), inv(n) {
    for (i64 k = 0; k < n; ++k) inv[perm[k]] = k;
  }
  void Reorder(const std::vector<i64>& post) {  // compose with post (new -> current)
    std::vector<i64> p(perm.size());
    for (size_t k = 0; k < p.size(); ++k) p[k] = perm[post[k]];
    perm.swap(p);
    for (size_t k = 0; k < perm.size(); ++k) inv[perm[k]] = i64(k);
  }
  i64 begin(i64 k) const { return colptr[perm[k]]; }
  i64 end(i64 k) const { return colptr[perm[k] + 1]; }
  i64 row(i64 p) const { return inv[rowind[p]]; }
};

// The elimination tree of P M Pᵀ (Liu's algorithm, path compression), from the rows above the
// diagonal of each column.
std::vector<i64> Etree(i64 n, const Permuted& A) {
  std::vector<i64> parent(n, -1), ancestor(n, -1);
  for (i64 k = 0; k < n; ++k)
    for (i64 p = A.begin(k); p < A.end(k); ++p) {
      i64 i = A.row(p);
      while (i != -1 && i < k) {
        const i64 up = ancestor[i];
        ancestor[i] = k;
        if (up == -1) parent[i] = k;
        i = up;
      }
    }
  return parent;
}

// A postorder of the forest `parent`: post[k] is the k-th node visited (children in index order).
std::vector<i64> Postorder(i64 n, const std::vector<i64>& parent) {
  std::vector<i64> head(n, -1), next(n, -1), post(n), stack;
  for (i64 j = n - 1; j >= 0; --j)
    if (parent[j] != -1) {
      next[j] = head[parent[j]];
      head[parent[j]] = j;
    }
  i64 k = 0;
  stack.reserve(n);
  for (i64 root = 0; root < n; ++root) {
    if (parent[root] != -1) continue;
    stack.push_back(root);
    while (!stack.empty()) {
      const i64 p = stack.back();
      const i64 child = head[p];
      if (child == -1) {
        stack.pop_back();
        post[k++] = p;
      } else {
        head[p] = next[child];
        stack.push_back(child);
      }
    }
  }
  return post;
}

bool Relax(i64 ncols, double zeros, double stored) {
  // CHOLMOD's default amalgamation: always up to 4 columns, then within a share of explicit zeros
  // (other settings, lighter or heavier, measured no faster in the factorisation or the solves)
  const double share = stored > 0 ? zeros / stored : 0.0;
  return ncols <= 4 || (ncols <= 16 && share < 0.8) || (ncols <= 48 && share < 0.1) || share < 0.05;
}

// The symbolic analysis: the ordering composed with a postorder (A is reordered), the supernodes
// and their rows.
void Analyse(Symbolic& f, i64 n, Permuted& A) {
  std::vector<i64> parent = Etree(n, A);
  {
    const std::vector<i64> post = Postorder(n, parent);
    std::vector<i64> place(n), relabelled(n);  // a postorder relabels the tree, not its shape
    for (i64 k = 0; k < n; ++k) place[post[k]] = k;
    for (i64 j = 0; j < n; ++j) relabelled[place[j]] = parent[j] == -1 ? -1 : place[parent[j]];
    A.Reorder(post);
    parent.swap(relabelled);
  }
  f.perm = A.perm;

  // column counts (with the diagonal): row k of L is the union of the paths from each j < k with
  // M(k, j) != 0 up the tree to k
  std::vector<i64> count(n, 1), flag(n, -1);
  for (i64 k = 0; k < n; ++k) {
    flag[k] = k;
    for (i64 p = A.begin(k); p < A.end(k); ++p)
      for (i64 j = A.row(p); j < k && flag[j] != k; j = parent[j]) {
        ++count[j];
        flag[j] = k;
      }
  }

  // fundamental supernodes (a column joins the one before where it is that column's parent and
  // their structures agree), amalgamated with the supernode before where that is a child of it
  struct Node {
    i64 first, ncols, nbelow;
    double nnz;  // the structural non-zeros of its columns
  };
  std::vector<Node> nodes;
  std::vector<i64> owner(n);  // column -> fundamental supernode, then -> final supernode
  for (i64 j = 0; j < n; ++j) {
    if (j > 0 && parent[j - 1] == j && count[j - 1] == count[j] + 1) {
      Node& s = nodes.back();
      ++s.ncols;
      s.nbelow = count[j] - 1;
      s.nnz += double(count[j]);
    } else {
      nodes.push_back({j, 1, count[j] - 1, double(count[j])});
    }
    owner[j] = i64(nodes.size()) - 1;
  }
  std::vector<Node> merged;
  std::vector<i64> to_merged(nodes.size());
  for (size_t s = 0; s < nodes.size(); ++s) {
    const Node& p = nodes[s];
    if (!merged.empty()) {
      Node& c = merged.back();
      const i64 last = c.first + c.ncols - 1;
      if (last + 1 == p.first && parent[last] != -1 && owner[parent[last]] == i64(s)) {
        const i64 nc = c.ncols + p.ncols, rows = nc + p.nbelow;
        const double stored = double(nc) * double(rows) - 0.5 * double(nc) * double(nc - 1);
        if (Relax(nc, stored - (c.nnz + p.nnz), stored)) {
          c.ncols = nc;
          c.nbelow = p.nbelow;
          c.nnz += p.nnz;
          to_merged[s] = i64(merged.size()) - 1;
          continue;
        }
      }
    }
    merged.push_back(p);
    to_merged[s] = i64(merged.size()) - 1;
  }
  const i64 ns = i64(merged.size());
  for (i64 j = 0; j < n; ++j) owner[j] = to_merged[owner[j]];
  f.supers.resize(ns);
  for (i64 s = 0; s < ns; ++s) {
    Super& S = f.supers[s];
    S.first = merged[s].first;
    S.ncols = merged[s].ncols;
    const i64 last = S.first + S.ncols - 1;
    S.parent = parent[last] == -1 ? -1 : owner[parent[last]];
    if (S.parent != -1) ++f.supers[S.parent].nchildren;
  }

  // each supernode's rows below: its columns' entries past its last column, and its children's
  // rows below past it (children come first in postorder)
  std::vector<i64> head(ns, -1), next(ns, -1);
  for (i64 s = ns - 1; s >= 0; --s) {
    const i64 p = f.supers[s].parent;
    if (p != -1) {
      next[s] = head[p];
      head[p] = s;
    }
  }
  std::fill(flag.begin(), flag.end(), -1);
  std::vector<i64> rows;
  f.rows.clear();
  for (i64 s = 0; s < ns; ++s) {
    Super& S = f.supers[s];
    const i64 last = S.first + S.ncols - 1;
    rows.clear();
    for (i64 j = S.first; j <= last; ++j)
      for (i64 p = A.begin(j); p < A.end(j); ++p) {
        const i64 r = A.row(p);
        if (r > last && flag[r] != s) {
          flag[r] = s;
          rows.push_back(r);
        }
      }
    for (i64 c = head[s]; c != -1; c = next[c]) {
      const Super& C = f.supers[c];
      for (i64 q = C.below_at; q < C.below_at + C.nbelow; ++q) {
        const i64 r = f.rows[q];
        if (r > last && flag[r] != s) {
          flag[r] = s;
          rows.push_back(r);
        }
      }
    }
    std::sort(rows.begin(), rows.end());
    S.below_at = i64(f.rows.size());
    S.nbelow = i64(rows.size());
    f.rows.insert(f.rows.end(), rows.begin(), rows.end());
    f.max_below = std::max(f.max_below, S.nbelow);
  }
  i64 at = 0;
  for (Super& S : f.supers) {
    S.lx_at = at;
    at += S.rows() * S.ncols;
  }
  f.lx_size = at;
}

const i64 kOutside = -2;  // Numeric's status: an entry of the matrix outside the analysed pattern

// The numeric factorisation of A (in the analysis's ordering) into F.lx: 0, the (1-based) column
// whose pivot is not positive, or kOutside.
i64 Numeric(Factor& F, const Permuted& A) {
  const Symbolic& f = *F.sym;
  const i64 n = f.n;
  F.lx.reset(new double[size_t(std::max<i64>(f.lx_size, 1))]);
  std::vector<i64> local(n, 0);  // row -> its place in the current front, past the supernode's columns
  struct Update {
    i64 super;
    std::unique_ptr<double[]> u;  // nbelow × nbelow, column-major, its lower triangle
    std::vector<i64> place;
  };
  std::vector<Update> stack;
  const char lo = 'L', no = 'N', tr = 'T', right = 'R';
  const double one = 1.0, minus = -1.0, zero = 0.0;
  for (i64 s = 0; s < i64(f.supers.size()); ++s) {
    const Super& S = f.supers[s];
    const i64 nc = S.ncols, nb = S.nbelow, m = S.rows(), last = S.first + nc - 1;
    const i64* below = f.rows.data() + S.below_at;
    for (i64 q = 0; q < nb; ++q) local[below[q]] = nc + q;
    double* L = F.lx.get() + S.lx_at;  // m × nc
    std::fill(L, L + m * nc, 0.0);
    for (i64 j = S.first; j <= last; ++j) {
      double* col = L + (j - S.first) * m;
      for (i64 p = A.begin(j); p < A.end(j); ++p) {
        const i64 r = A.row(p);
        if (r < j) continue;
        if (r <= last) {
          col[r - S.first] += A.val[p];
          continue;
        }
        const i64 q = local[r] - nc;  // (a row of another supernode's leaves a stale place)
        if (q < 0 || q >= nb || below[q] != r) return kOutside;
        col[nc + q] += A.val[p];
      }
    }
    // the children's update matrices (the last nchildren on the stack): their columns within the
    // supernode's now, the rest once the update matrix U = -L21 L21ᵀ is made
    const i64 nch = S.nchildren, from = i64(stack.size()) - nch;
    for (i64 c = from; c < i64(stack.size()); ++c) {
      const Super& C = f.supers[stack[c].super];
      const i64 cb = C.nbelow;
      const i64* crow = f.rows.data() + C.below_at;
      std::vector<i64>& place = stack[c].place;  // the child's rows' places in this front
      place.resize(cb);
      for (i64 q = 0; q < cb; ++q) place[q] = crow[q] <= last ? crow[q] - S.first : local[crow[q]];
      const double* cu = stack[c].u.get();
      for (i64 b = 0; b < cb && place[b] < nc; ++b) {
        double* dst = L + place[b] * m;
        const double* src = cu + b * cb;
        for (i64 a = b; a < cb; ++a) dst[place[a]] += src[a];
      }
    }
    const int inc = int(nc), inm = int(m), inb = int(nb);
    int info = 0;
    blas.potrf(&lo, &inc, L, &inm, &info);
    if (info != 0) return S.first + (info > 0 ? info : 1);
    std::unique_ptr<double[]> U;
    if (nb > 0) {
      U.reset(new double[size_t(nb) * size_t(nb)]);
      blas.trsm(&right, &lo, &tr, &no, &inb, &inc, &one, L, &inm, L + nc, &inm);
      blas.syrk(&lo, &no, &inb, &inc, &minus, L + nc, &inm, &zero, U.get(), &inb);
    }
    for (i64 c = from; c < i64(stack.size()); ++c) {
      const i64 cb = f.supers[stack[c].super].nbelow;
      const i64* place = stack[c].place.data();
      const double* cu = stack[c].u.get();
      i64 b0 = 0;
      while (b0 < cb && place[b0] < nc) ++b0;
      for (i64 b = b0; b < cb; ++b) {  // (a place past the supernode's columns is U's row or column + nc)
        double* dst = U.get() + (place[b] - nc) * nb;
        const double* src = cu + b * cb;
        for (i64 a = b; a < cb; ++a) dst[place[a] - nc] += src[a];
      }
    }
    stack.resize(stack.size() - nch);
    if (S.parent != -1) stack.push_back({s, std::move(U), {}});
  }
  return 0;
}

// x's rows `below` less t's (nb × k, row-major)
void Scatter(double* x, const i64* below, i64 nb, i64 k, const double* t) {
  if (k == 1) {
    for (i64 q = 0; q < nb; ++q) x[below[q]] -= t[q];
    return;
  }
  for (i64 q = 0; q < nb; ++q) {
    double* xr = x + below[q] * k;
    const double* tq = t + q * k;
    for (i64 c = 0; c < k; ++c) xr[c] -= tq[c];
  }
}

// a · b over n entries, in four partial sums
double Dot(const double* a, const double* b, i64 n) {
  double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
  i64 i = 0;
  for (; i + 4 <= n; i += 4) {
    s0 += a[i] * b[i];
    s1 += a[i + 1] * b[i + 1];
    s2 += a[i + 2] * b[i + 2];
    s3 += a[i + 3] * b[i + 3];
  }
  for (; i < n; ++i) s0 += a[i] * b[i];
  return (s0 + s1) + (s2 + s3);
}

// Whether a supernode of `size` entries (its rows × columns) is solved by hand for k columns.
bool ByHand(i64 k, i64 size) { return k == 1 || size * k < kBlasSolve; }

// fn(std::integral_constant<int, K>), K the column count where it is one of the few compiled
// for, else 0 (any count, k read at run time). Compiled for, the loops over the columns unroll:
// a 55k-scalar channel of a 256² map solved one column in 8.4-8.9 against 9.7-10.6 ms, two in
// 15-16 against 18-22 ms, three in 17-19 against 21-23 ms (four, whose large supernodes go
// through BLAS: 19-22 ms either way). The arithmetic per column is the same, to the bit.
template <typename Fn>
void WithColumns(i64 k, Fn fn) {
  switch (k) {
    case 1: return fn(std::integral_constant<int, 1>());
    case 2: return fn(std::integral_constant<int, 2>());
    case 3: return fn(std::integral_constant<int, 3>());
    case 4: return fn(std::integral_constant<int, 4>());
    case 8: return fn(std::integral_constant<int, 8>());
    default: return fn(std::integral_constant<int, 0>());
  }
}

// The forward solve's supernode (columns xs of x, its rows below scattered), by hand: K columns
// (0: k of them).
template <int K>
void ForwardByHand(const double* L, i64 nc, i64 nb, i64 m, const i64* below, double* x, double* xs, double* tq,
                   i64 k) {
  const i64 kk = K > 0 ? K : k;
  for (i64 j = 0; j < nc; ++j) {  // the diagonal block
    const double* col = L + j * m;
    double* xj = xs + j * kk;
    const double d = col[j];
    for (i64 c = 0; c < kk; ++c) xj[c] /= d;
    for (i64 i = j + 1; i < nc; ++i) {
      double* xi = xs + i * kk;
      const double l = col[i];
      for (i64 c = 0; c < kk; ++c) xi[c] -= l * xj[c];
    }
  }
  if (nb == 0) return;
  std::fill(tq, tq + nb * kk, 0.0);  // t = L21 x_s, then scattered
  for (i64 j = 0; j < nc; ++j) {
    const double* col = L + j * m + nc;
    const double* xj = xs + j * kk;
    if (kk == 1) {
      const double v = xj[0];
      for (i64 q = 0; q < nb; ++q) tq[q] += col[q] * v;
    } else {
      for (i64 q = 0; q < nb; ++q)
        for (i64 c = 0; c < kk; ++c) tq[q * kk + c] += col[q] * xj[c];
    }
  }
  Scatter(x, below, nb, kk, tq);
}

// The backward solve's supernode, by hand: K columns (0: k of them).
template <int K>
void BackwardByHand(const double* L, i64 nc, i64 nb, i64 m, const i64* below, const double* x, double* xs,
                    double* tq, i64 k) {
  const i64 kk = K > 0 ? K : k;
  for (i64 q = 0; q < nb; ++q) std::memcpy(tq + q * kk, x + below[q] * kk, sizeof(double) * size_t(kk));  // x's rows below
  for (i64 j = nc - 1; j >= 0; --j) {
    const double* col = L + j * m;
    double* xj = xs + j * kk;
    if (kk == 1) {
      xj[0] = (xj[0] - Dot(col + nc, tq, nb) - Dot(col + j + 1, xj + 1, nc - j - 1)) / col[j];
      continue;
    }
    for (i64 q = 0; q < nb; ++q) {
      const double l = col[nc + q];
      for (i64 c = 0; c < kk; ++c) xj[c] -= l * tq[q * kk + c];
    }
    for (i64 i = j + 1; i < nc; ++i) {
      const double* xi = xs + i * kk;
      const double l = col[i];
      for (i64 c = 0; c < kk; ++c) xj[c] -= l * xi[c];
    }
    const double d = col[j];
    for (i64 c = 0; c < kk; ++c) xj[c] /= d;
  }
}

}  // namespace

extern "C" {

// The BLAS and LAPACK routines (Fortran interface): gemm, syrk, trsm, potrf.
void diffshade_chol_set_blas(void** fn) {
  blas.gemm = reinterpret_cast<dgemm_t>(fn[0]);
  blas.syrk = reinterpret_cast<dsyrk_t>(fn[1]);
  blas.trsm = reinterpret_cast<dtrsm_t>(fn[2]);
  blas.potrf = reinterpret_cast<dpotrf_t>(fn[3]);
  FindThreadControl(fn[0]);
}

// Whether OpenBLAS's thread count is held at one during the work (its functions were found).
int diffshade_chol_holds_threads() { return set_threads != nullptr; }

// OpenBLAS's thread count now (-1 where its functions were not found).
int diffshade_chol_blas_threads() { return get_threads ? get_threads() : -1; }

// The symbolic analysis of the symmetric n × n pattern (CSC, both triangles; only the entries on
// or below the diagonal of the permuted matrix are read) in the ordering `order` (new -> old)
// composed with a postorder. Returns its handle, or null with *status -1 (no memory).
void* diffshade_chol_analyse(i64 n, const i64* colptr, const i64* rowind, const i64* order, i64* status) {
  *status = 0;
  try {
    std::shared_ptr<Symbolic> f(new Symbolic());
    f->n = n;
    Permuted A(n, colptr, rowind, nullptr, order);
    Analyse(*f, n, A);
    return new std::shared_ptr<const Symbolic>(std::move(f));
  } catch (const std::bad_alloc&) {
    *status = -1;
    return nullptr;
  }
}

// Factorise the symmetric matrix (CSC as the analysis's, its stored entries within the analysed
// pattern) by the analysis `sym`. Returns the factor, or null with *status the failing column
// (1-based), -1 (no memory) or -2 (an entry outside the analysed pattern).
void* diffshade_chol_numeric(void* sym, const i64* colptr, const i64* rowind, const double* val, i64* status) {
  *status = 0;
  OneBlasThread single;
  try {
    std::unique_ptr<Factor> f(new Factor());
    f->sym = *static_cast<std::shared_ptr<const Symbolic>*>(sym);
    Permuted A(f->sym->n, colptr, rowind, val, f->sym->perm.data());
    const i64 bad = Numeric(*f, A);
    if (bad != 0) {
      *status = bad;
      return nullptr;
    }
    return f.release();
  } catch (const std::bad_alloc&) {
    *status = -1;
    return nullptr;
  }
}

// The analysis's final ordering (new -> the caller's index), n entries.
void diffshade_chol_perm(void* sym, i64* out) {
  const Symbolic& f = **static_cast<std::shared_ptr<const Symbolic>*>(sym);
  std::copy(f.perm.begin(), f.perm.end(), out);
}

// The analysis's stored entries of L (explicit zeros of the amalgamation included) and its number
// of supernodes.
void diffshade_chol_stats(void* sym, i64* out) {
  const Symbolic& f = **static_cast<std::shared_ptr<const Symbolic>*>(sym);
  out[0] = f.lx_size;
  out[1] = i64(f.supers.size());
}

void diffshade_chol_analysis_free(void* sym) { delete static_cast<std::shared_ptr<const Symbolic>*>(sym); }

// Solve L Lᵀ x = b in place for k columns (x: n × k, row-major: a row's k values together, in the
// final ordering). Small supernodes are solved by hand, row by row of k values; large ones through
// BLAS on xᵀ (k × n, column-major). Returns 0, or -1 without memory.
int diffshade_chol_solve(void* h, double* x, i64 k) {
  const Factor& F = *static_cast<Factor*>(h);
  const Symbolic& f = *F.sym;
  OneBlasThread single;
  std::vector<double> t;
  try {
    t.resize(size_t(std::max<i64>(f.max_below, 1)) * size_t(k));
  } catch (const std::bad_alloc&) {
    return -1;
  }
  const char lo = 'L', no = 'N', tr = 'T', right = 'R';
  const double one = 1.0, zero = 0.0, minus = -1.0;
  const int ik = int(k);
  // forward: L y = b
  for (const Super& S : f.supers) {
    const i64 nc = S.ncols, nb = S.nbelow, m = S.rows();
    const double* L = F.lx.get() + S.lx_at;
    const i64* below = f.rows.data() + S.below_at;
    double* xs = x + S.first * k;
    if (ByHand(k, nc * m)) {
      WithColumns(k, [&](auto kc) { ForwardByHand<decltype(kc)::value>(L, nc, nb, m, below, x, xs, t.data(), k); });
      continue;
    }
    const int inc = int(nc), inm = int(m), inb = int(nb);
    blas.trsm(&right, &lo, &tr, &no, &ik, &inc, &one, L, &inm, xs, &ik);
    if (nb == 0) continue;
    blas.gemm(&no, &tr, &ik, &inb, &inc, &one, xs, &ik, L + nc, &inm, &zero, t.data(), &ik);
    Scatter(x, below, nb, k, t.data());
  }
  // backward: Lᵀ x = y
  for (i64 s = i64(f.supers.size()) - 1; s >= 0; --s) {
    const Super& S = f.supers[s];
    const i64 nc = S.ncols, nb = S.nbelow, m = S.rows();
    const double* L = F.lx.get() + S.lx_at;
    const i64* below = f.rows.data() + S.below_at;
    double* xs = x + S.first * k;
    if (ByHand(k, nc * m)) {
      WithColumns(k, [&](auto kc) { BackwardByHand<decltype(kc)::value>(L, nc, nb, m, below, x, xs, t.data(), k); });
      continue;
    }
    const int inc = int(nc), inm = int(m), inb = int(nb);
    if (nb > 0) {
      for (i64 q = 0; q < nb; ++q) std::memcpy(t.data() + q * k, x + below[q] * k, sizeof(double) * size_t(k));
      blas.gemm(&no, &no, &ik, &inc, &inb, &minus, t.data(), &ik, L + nc, &inm, &one, xs, &ik);
    }
    blas.trsm(&right, &lo, &no, &no, &ik, &inc, &one, L, &inm, xs, &ik);
  }
  return 0;
}

// The diagonal of M⁻¹ (n entries, in the final ordering) by selected inversion (Takahashi's
// equations over the supernodes, from the root down): for a supernode s with rows R below it and
// Y = L_Rs L_ss⁻¹, Z_Rs = -Z_RR Y and Z_ss = L_ss⁻ᵀ L_ss⁻¹ - Yᵀ Z_Rs, where Z_RR, the inverse on R,
// lies in the parent's front (R is within the parent's columns and rows). Each supernode with
// children keeps its front (its Z on its columns and rows) until they are done. Returns 0, or -1
// without memory.
int diffshade_chol_inverse_diagonal(void* h, double* out) {
  const Factor& F = *static_cast<Factor*>(h);
  const Symbolic& f = *F.sym;
  OneBlasThread single;
  const char lo = 'L', no = 'N', tr = 'T', right = 'R', left = 'L';
  const double one = 1.0, zero = 0.0, minus = -1.0;
  struct Front {
    i64 super;
    std::vector<double> z;  // m × m, column-major, both triangles
  };
  try {
    std::vector<Front> stack;
    std::vector<double> y, zrr, zrs, w;
    std::vector<i64> place;
    for (i64 s = i64(f.supers.size()) - 1; s >= 0; --s) {
      const Super& S = f.supers[s];
      const i64 nc = S.ncols, nb = S.nbelow, m = S.rows();
      const double* L = F.lx.get() + S.lx_at;
      const i64* below = f.rows.data() + S.below_at;
      while (!stack.empty() && stack.back().super != S.parent) stack.pop_back();
      const int inc = int(nc), inm = int(m), inb = int(nb);
      // W = L_ss⁻ᵀ L_ss⁻¹ (its lower triangle): L_ss⁻¹ by TRSM on the identity, then SYRK
      std::vector<double> x(size_t(nc) * size_t(nc), 0.0);
      for (i64 j = 0; j < nc; ++j) x[size_t(j) * size_t(nc) + size_t(j)] = 1.0;
      blas.trsm(&left, &lo, &no, &no, &inc, &inc, &one, L, &inm, x.data(), &inc);
      w.assign(size_t(nc) * size_t(nc), 0.0);
      blas.syrk(&lo, &tr, &inc, &inc, &one, x.data(), &inc, &zero, w.data(), &inc);
      if (nb > 0) {
        if (stack.empty()) return -2;  // (a supernode with rows below has a parent, whose front is kept)
        const Front& P = stack.back();
        const Super& PS = f.supers[P.super];
        const i64 pm = PS.rows(), plast = PS.first + PS.ncols - 1;
        const i64* pbelow = f.rows.data() + PS.below_at;
        place.resize(size_t(nb));
        for (i64 q = 0; q < nb; ++q) {
          const i64 r = below[q];
          place[q] = r <= plast ? r - PS.first
                                : PS.ncols + (std::lower_bound(pbelow, pbelow + PS.nbelow, r) - pbelow);
        }
        zrr.resize(size_t(nb) * size_t(nb));
        for (i64 j = 0; j < nb; ++j) {
          const double* src = P.z.data() + size_t(place[j]) * size_t(pm);
          double* dst = zrr.data() + size_t(j) * size_t(nb);
          for (i64 i = 0; i < nb; ++i) dst[i] = src[place[i]];
        }
        y.resize(size_t(nb) * size_t(nc));  // Y = L_Rs L_ss⁻¹
        for (i64 j = 0; j < nc; ++j) std::memcpy(y.data() + size_t(j) * size_t(nb), L + j * m + nc, sizeof(double) * size_t(nb));
        blas.trsm(&right, &lo, &no, &no, &inb, &inc, &one, L, &inm, y.data(), &inb);
        zrs.resize(size_t(nb) * size_t(nc));  // Z_Rs = -Z_RR Y
        blas.gemm(&no, &no, &inb, &inc, &inb, &minus, zrr.data(), &inb, y.data(), &inb, &zero, zrs.data(), &inb);
        blas.gemm(&tr, &no, &inc, &inc, &inb, &minus, y.data(), &inb, zrs.data(), &inb, &one, w.data(), &inc);
      }
      for (i64 j = 0; j < nc; ++j) out[S.first + j] = w[size_t(j) * size_t(nc) + size_t(j)];
      if (S.nchildren == 0) continue;
      Front fr{s, std::vector<double>(size_t(m) * size_t(m))};
      double* z = fr.z.data();
      for (i64 j = 0; j < nc; ++j)
        for (i64 i = j; i < nc; ++i) {
          const double v = w[size_t(j) * size_t(nc) + size_t(i)];
          z[size_t(j) * size_t(m) + size_t(i)] = v;
          z[size_t(i) * size_t(m) + size_t(j)] = v;
        }
      for (i64 j = 0; j < nc; ++j)
        for (i64 i = 0; i < nb; ++i) {
          const double v = zrs[size_t(j) * size_t(nb) + size_t(i)];
          z[size_t(j) * size_t(m) + size_t(nc + i)] = v;
          z[size_t(nc + i) * size_t(m) + size_t(j)] = v;
        }
      for (i64 j = 0; j < nb; ++j)
        std::memcpy(z + size_t(nc + j) * size_t(m) + size_t(nc), zrr.data() + size_t(j) * size_t(nb), sizeof(double) * size_t(nb));
      stack.push_back(std::move(fr));
    }
  } catch (const std::bad_alloc&) {
    return -1;
  }
  return 0;
}

void diffshade_chol_free(void* h) { delete static_cast<Factor*>(h); }

}  // extern "C"
