r"""The linear block: which parameters the image is linear in, the bounded linear least squares
that solves them, and the reduced problem of the others (variable projection).

**Variable projection** (Golub & Pereyra 1973; Kaufman's Jacobian). The image is affine in the
*linear* parameters :math:`x` (reflectances :math:`k_a, k_d, k_s, k_t`, emission, fog colour, and
light colours when no :math:`k` they multiply is free): for fixed nonlinear parameters
:math:`\theta` (exponent, attenuation, fog density, spot, :math:`\eta`, opacity, …)
:math:`r(x, \theta) = A(\theta)\,x + b(\theta) - y`. One forward-mode pass gives :math:`b` and the
columns of :math:`A` (a tangent per linear *field*: every term is per colour channel, so the
tangent with ones in a field's three channels gives its three columns at once). The linear block
is then solved exactly under its bounds (:func:`bounded_lsq`; :math:`k \in [0, 1]`, colours
:math:`\ge 0`), so it needs no start and reaches or leaves a bound exactly, and optimistix's
Levenberg–Marquardt moves only :math:`\theta` on the reduced residual
:math:`r(x^*(\theta), \theta)` with Kaufman's Jacobian :math:`P^\perp_{A_ full, censored residual; it also produces the Jacobian for the standard errors.

With ``clamp`` on, nothing is linear: the same machinery runs with every parameter nonlinear
(plain LM from the global start); the result says so.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import keep

from . import _options
from ._problem import Problem, tangent_images, view_list

_LINEAR_MATERIAL = {"emission", "ambient", "diffuse", "specular", "transmission"}
# which material fields a light field multiplies (both free: the light's side is nonlinear)
_PRODUCT = {"color": {"diffuse", "specular", "transmission"}, "ambient": {"ambient"}, "specular": {"specular"}}


def _is_linear_candidate(p) -> bool:
    """A parameter the image is linear in when it is the only one of its product free."""
    kind, field = p.path[0], p.path[-1]
    if kind in ("material", "materials", "back_material"):
        return field in _LINEAR_MATERIAL
    if kind in ("directional", "point", "spot", "area", "multi_lobe"):
        return field in _PRODUCT
    return p.path in (("ambient_light",), ("fog", "color"))


def split_linear(pset, opts, scene=None) -> tuple[list[int], dict[str, str]]:
    """Indices (into ``pset.params``) of the parameters the image is linear in, and for each other
    parameter why it is not (``scene`` tells which light kinds have separate specular colours)."""
    names = [p.path for p in pset.params]
    free_mat_fields = {p.path[-1] for p in pset.params if p.path[0] in ("material", "materials", "back_material")}
    linear, why = [], {}
    for i, p in enumerate(pset.params):
        kind, field = p.path[0], p.path[-1]
        if _options.clamp(opts):
            why[p.name] = "clamp = true: the image is not linear in any parameter"
            continue
        if kind in ("material", "materials", "back_material"):
            ok = field in _LINEAR_MATERIAL
        elif kind in ("directional", "point", "spot", "area", "multi_lobe"):
            product = _PRODUCT.get(field, set())
            if field == "color" and scene is not None and getattr(getattr(scene, kind), "specular", None) is not None:
                product = product - {"specular"}  # a separate specular colour lights the specular term
            ok = field in _PRODUCT and not (product & free_mat_fields)
            if field in _PRODUCT and not ok:
                why[p.name] = f"multiplies a free material {'/'.join(sorted(product & free_mat_fields))}"
                continue
        elif p.path == ("ambient_light",):
            ok = "ambient" not in free_mat_fields
            if not ok:
                why[p.name] = "multiplies a free material ambient"
                continue
        elif p.path in (("camera", "exposure"), ("camera", "white_balance")):
            # the gain multiplies the whole image: linear unless another linear candidate (a k,
            # a light colour, ...) or another gain of the same view is free
            others = [
                q
                for j, q in enumerate(pset.params)
                if j != i
                and (
                    _is_linear_candidate(q)
                    or (
                        q.path[0] == "camera"
                        and q.path[1] in ("exposure", "white_balance")
                        and (q.view is None or p.view is None or q.view == p.view)
                    )
                )
            ]
            ok = not others
            if not ok:
                why[p.name] = f"multiplies the image, and {others[0].name} is free"
                continue
        else:
            ok = p.path in (("fog", "color"), ("camera", "black_level"))  # (additive: the image is affine in them)
        if ok:
            linear.append(i)
        else:
            why[p.name] = "nonlinear"
    del names
    return linear, why


# --------------------------------------------------------------------------------------------
# Bounded linear least squares
# --------------------------------------------------------------------------------------------


def _pinv(G, free, rcond):
    """``(P, f)``: the pseudo-inverse ``P`` of ``G``'s free block (``G_ff⁺``, zero off the free
    set) as a matrix, and the free set ``f`` it has (``free`` where ``G``'s diagonal is not 0)."""
    # Jacobi scaling first: the pseudo-inverse's cut is then relative to correlations, not to
    # the parameters' units (unscaled, a weakly-scaled parameter's step would be cut to 0).
    dg = jnp.diag(G)
    f = free & (dg > 0)
    fr = jnp.where(f, 1.0 / jnp.sqrt(jnp.where(f, dg, 1.0)), 0.0)
    M = G * fr[:, None] * fr[None, :] + jnp.diag(jnp.where(f, 0.0, 1.0).astype(G.dtype))
    w, V = jnp.linalg.eigh(M)
    inv = jnp.where(w > rcond * jnp.max(w), 1.0 / jnp.where(w > 0, w, 1.0), 0.0)
    W = V * fr[:, None]
    return (W * inv) @ W.T, f


def _masked_solve(G, rhs, free, rcond):
    """``d`` with ``G_ff d_f = rhs_f`` (pseudo-inverse), ``d = 0`` off the free set; ``rhs`` a
    vector or a matrix (columns)."""
    return _pinv(G, free, rcond)[0] @ rhs


class LinearSolution(NamedTuple):
    """:func:`bounded_lsq_solver`'s optimum ``x``, its ``free`` variables, and what solves their
    normal equations (a pytree of arrays: it passes through ``lax.cond``)."""

    x: jax.Array
    free: jax.Array
    inverse: jax.Array  # (A_fᵀA_f)⁺: the pseudo-inverse of the free variables' normal matrix
    gram: jax.Array  # A_fᵀA_f: the normal matrix of the free variables (0 elsewhere)

    def solve(self, rhs):
        """``c`` with ``(A_fᵀA_f) c = rhs`` on the free variables (0 elsewhere)."""
        return self.inverse @ rhs

    @classmethod
    def none(cls, x):
        """No solution: ``x`` kept, nothing free, every solve 0."""
        n, dt = x.shape[0], x.dtype
        return cls(x, jnp.zeros(n, bool), jnp.zeros((n, n), dt), jnp.zeros((n, n), dt))


def bounded_lsq(A, r0, lo, hi, x0, iters: int | None = None):
    r"""``argmin ‖A x + r0‖²`` subject to ``lo ≤ x ≤ hi`` (``hi`` may be inf), for a few columns;
    ``(x, free)`` of :func:`bounded_lsq_solver`."""
    sol = bounded_lsq_solver(A, r0, lo, hi, x0, iters)
    return sol.x, sol.free


def bounded_lsq_solver(A, r0, lo, hi, x0, iters: int | None = None, refine: int = 2):
    r"""``argmin ‖A x + r0‖²`` subject to ``lo ≤ x ≤ hi`` (``hi`` may be inf), for a few columns.

    The primal active-set method (Nocedal & Wright, Alg. 16.3) on the column-scaled normal
    equations, with the working set carried from step to step: at the subspace optimum the
    variable of the working set with the most negative multiplier leaves it; then a Newton step
    on the free variables, which, if it leaves the box, is cut where it meets the first bound,
    which joins the working set. It ends after two steps in a row that neither met a bound nor
    released one, in at most ``iters`` (static; a few times ``n``). Then ``refine`` steps on
    that free set with the gradient :math:`A^T(Ax + r_0)` taken from the residual (iterative
    refinement: float32 normal equations lose :math:`\mathrm{cond}^2` digits), each with the
    last step's eigendecomposition (one in the program, in the loop). Columns that are zero (a
    term the image does not show) keep ``x0``.

    Returns a :class:`LinearSolution`: ``free`` marks the variables the last step held free
    (inside their bounds), and its ``solve`` and ``gram`` are their normal equations with that
    step's eigendecomposition (variable projection's Kaufman Jacobian needs them at the solution).
    """
    At = A.T  # [n, M]: each column a row (products over the rows need no transposed copy)
    n = At.shape[0]
    iters = 4 * n + 4 if iters is None else iters
    dt = At.dtype
    eps = float(jnp.finfo(dt).eps)
    s = jnp.sqrt(jnp.sum(At * At, axis=1))
    det = s > 1e3 * eps * jnp.max(s)
    inv_s = jnp.where(det, 1.0 / jnp.where(det, s, 1.0), 0.0)
    As = At * inv_s[:, None]
    G = As @ As.T
    c = As @ r0
    # scaled variables y = s x; undetermined ones fixed at s x0 (their column is ~0 anyway)
    ylo, yhi = lo * s, jnp.where(jnp.isinf(hi), jnp.inf, hi * s)
    rcond = 1e2 * eps
    big = jnp.asarray(jnp.inf, dt)
    idx = jnp.arange(n)

    def body(carry):
        k, y, w_lo, w_hi, blocked_prev, n_opt, _ = carry
        g = G @ y + c
        # at the subspace optimum: release the working-set variable with the most negative multiplier
        lam = jnp.where(w_lo, g, jnp.where(w_hi, -g, big))
        worst = jnp.argmin(lam)
        release = ~blocked_prev & (lam[worst] < -1e2 * eps * (1.0 + jnp.max(jnp.abs(g))))
        w_lo, w_hi = w_lo & ~(release & (idx == worst)), w_hi & ~(release & (idx == worst))
        P, free = _pinv(G, det & ~w_lo & ~w_hi, rcond)
        d = -(P @ g)
        room = jnp.where(
            d < 0, (ylo - y) / jnp.where(d < 0, d, -1.0), jnp.where(d > 0, (yhi - y) / jnp.where(d > 0, d, 1.0), big)
        )
        room = jnp.where(free, jnp.maximum(room, 0.0), big)
        alpha = jnp.minimum(jnp.min(room), 1.0)
        blocked = alpha < 1.0
        hit = blocked & (idx == jnp.argmin(room))
        y = jnp.clip(jnp.where(free, y + alpha * d, y), ylo, yhi)
        n_opt = jnp.where(blocked | release, 0, n_opt + 1)
        return k + 1, y, w_lo | (hit & (d < 0)), w_hi | (hit & (d > 0)), blocked, n_opt, (P, free)

    # from the start clipped into the box with an empty working set
    y0 = x0 * s
    none = jnp.zeros(n, bool)
    carry = (jnp.asarray(0), jnp.where(det, jnp.clip(y0, ylo, yhi), y0), none, none, jnp.asarray(True), 0)
    carry += ((jnp.zeros((n, n), dt), none),)
    _, y, _, _, _, _, (P, free) = jax.lax.while_loop(lambda c: (c[5] < 2) & (c[0] < iters), body, carry)
    for _ in range(refine):
        g = As @ (y @ As + r0)
        y = jnp.clip(jnp.where(free, y - P @ g, y), ylo, yhi)
    x = jnp.where(det, y * inv_s, x0)
    sf = s * free
    return LinearSolution(x, free, P * inv_s[:, None] * inv_s[None, :], G * sf[:, None] * sf[None, :])


# --------------------------------------------------------------------------------------------
# The reduced problem
# --------------------------------------------------------------------------------------------


def in_view(views, rows, dt):
    """``[n, M]``: 1 where scalar ``i``'s column may be non-zero (a shared scalar's, view -1,
    everywhere; a per-view one's on its view's ``rows``), 0 elsewhere."""
    views = jnp.asarray(views)[:, None]
    return ((views < 0) | (views == rows[None, :])).astype(dt)


class Reduced:
    """The variable-projection view of a :class:`Problem`: static index sets and the reduced
    residual of the nonlinear parameters (in the solver's unconstrained ``u``)."""

    def __init__(self, prob: Problem, linear: bool = True):
        self.prob = prob
        pset = prob.pset
        self.linear_params, self.why = split_linear(pset, prob.opts, prob.data[0].scene)
        if not linear:
            self.why.update({pset.params[i].name: "method = 'full' asked for" for i in self.linear_params})
            self.linear_params = []
        lin = set(self.linear_params)
        # the per-view parameters of one name (``view[1].camera.exposure``, ``view[2]...``) share a
        # tangent: each view's rows show its own scalar, so one pass of the render gives every
        # view's column (block-sparse: the others' rows are 0), not a pass per view
        base = lambda p: p.name.split(".", 1)[1] if p.view is not None else p.name  # noqa: E731
        groups, slots = {}, {}
        idx_l, idx_n, group, chan, lo, hi, view_l, slot, view_n = ([] for _ in range(9))
        for i, (p, off) in enumerate(zip(pset.params, pset.offsets[:-1])):
            sc = list(range(off, off + p.size))
            view = -1 if p.view is None else p.view
            if i in lin:
                g = groups.setdefault(base(p), len(groups))
                for c, j in enumerate(sc):
                    idx_l.append(j)
                    group.append(g)
                    view_l.append(view)
                    chan.append(np.eye(3)[c] if p.size == 3 else np.ones(3))
                    lo.append(p.box[0])
                    hi.append(p.box[1])
            else:
                for c, j in enumerate(sc):
                    idx_n.append(j)
                    slot.append(slots.setdefault((base(p), c), len(slots)))
                    view_n.append(view)
        self.idx_l, self.idx_n = np.asarray(idx_l, int), np.asarray(idx_n, int)
        self.group, self.slot = np.asarray(group, int), np.asarray(slot, int)
        self.view_l, self.view_n = np.asarray(view_l, int), np.asarray(view_n, int)
        self.chan = np.asarray(chan).reshape(-1, 3)
        self.lo, self.hi = np.asarray(lo), np.asarray(hi)
        self.n_groups, self.n_slots = len(groups), len(slots)
        self.per_view_l, self.per_view_n = bool((self.view_l >= 0).any()), bool((self.view_n >= 0).any())
        self.param_of = np.repeat(np.arange(len(pset.params)), pset.sizes)
        # θ's scalars from z = (x, u): scalar i is z[order[i]]
        self.order = np.empty(len(self.idx_l) + len(self.idx_n), int)
        self.order[self.idx_l] = np.arange(len(self.idx_l))
        self.order[self.idx_n] = len(self.idx_l) + np.arange(len(self.idx_n))
        self.is_linear = np.zeros(len(self.order), bool)
        self.is_linear[self.idx_l] = True

    @property
    def method(self) -> str:
        if not len(self.idx_l):
            reason = "; ".join(sorted(set(self.why.values())))
            return f"Levenberg–Marquardt on all parameters ({reason})"
        if not len(self.idx_n):
            return "bounded linear least squares (every free parameter enters the image linearly)"
        return (
            f"variable projection: {len(self.idx_l)} linear scalars solved exactly under their bounds, "
            f"Levenberg–Marquardt on {len(self.idx_n)} nonlinear"
        )

    # -- pieces -------------------------------------------------------------------------------
    def theta(self, u_n, x, theta_ref):
        """Full natural θ from the nonlinear ``u`` and the linear ``x`` (``theta_ref`` fills nothing
        else: every scalar is one or the other)."""
        z = jnp.concatenate([x.astype(theta_ref.dtype), u_n.astype(theta_ref.dtype)])[self.order]
        return jnp.where(self.is_linear, z, self.prob.pset.theta_from_u(z))

    def design(self, vd, theta):
        """``(A, b)`` of one view at its compacted pixels: ``b`` the image with the linear scalars
        at 0, ``A`` ``[N·3, n_lin]`` their columns (weighted by the two-sided weight)."""
        th0 = theta.at[self.idx_l].set(0.0)
        f = lambda xl: self.prob.image(vd, th0.at[self.idx_l].set(xl))  # noqa: E731
        E = np.zeros((self.n_groups, len(self.idx_l)))
        E[self.group, np.arange(len(self.idx_l))] = 1.0
        z = jnp.zeros(len(self.idx_l), theta.dtype)
        # vmap of jvp: the primal once, the tangents batched (10x faster than vmap of linearize's
        # linear function on XLA's CPU backend)
        b, T = tangent_images(f, z, jnp.asarray(E, theta.dtype))
        T, b = keep(T, b)  # materialised: XLA would otherwise recompute the render inside the gather below
        w = vd.weight * ~(vd.hi | vd.lo)
        mine = in_view(self.view_l, jnp.reshape(vd.index, (1,)), T.dtype)  # [n_lin, 1]: this view's scalars
        cols = T[self.group] * (jnp.asarray(self.chan, T.dtype) * mine)[:, None, :] * w  # [n_lin, N, 3]
        return cols.reshape(len(self.idx_l), -1).T, b

    def solve_linear(self, theta, data):
        """The bounded linear optimum ``x*`` at ``theta``'s nonlinear values (no gradient), with
        its free mask and the stacked design matrix."""
        As, r0s = [], []
        for vd in view_list(data):
            A, b = self.design(vd, theta)
            w = vd.weight * ~(vd.hi | vd.lo)
            As.append(A)
            r0s.append(((b - vd.target) * w).reshape(-1))
        A, r0 = jax.lax.stop_gradient((jnp.concatenate(As), jnp.concatenate(r0s)))
        x0 = jax.lax.stop_gradient(theta[self.idx_l])
        x, free = bounded_lsq(A, r0, jnp.asarray(self.lo, A.dtype), jnp.asarray(self.hi, A.dtype), x0)
        return x, free, A, r0

    def residual(self, u_n, args):
        """Reduced residual ``r(x*(θ), θ)`` (two-sided entries) with Kaufman's tangent; aux ``x*``."""
        data, theta_ref = args
        theta = self.theta(u_n, theta_ref[self.idx_l], theta_ref)
        if not len(self.idx_l):
            r = jnp.concatenate(
                [
                    ((self.prob.image(vd, theta) - vd.target) * vd.weight * ~(vd.hi | vd.lo)).reshape(-1)
                    for vd in view_list(data)
                ]
            )
            return r.astype(u_n.dtype), jnp.zeros((0,), theta.dtype)
        x, free, A, _ = self.solve_linear(theta, data)
        theta = theta.at[self.idx_l].set(x)
        r = jnp.concatenate(
            [
                ((self.prob.image(vd, theta) - vd.target) * vd.weight * ~(vd.hi | vd.lo)).reshape(-1)
                for vd in view_list(data)
            ]
        )
        # Kaufman: the tangent is projected off the span of the free linear columns
        Af = A * free.astype(A.dtype)
        G = Af.T @ Af
        Pr = Af @ _masked_solve(G, Af.T @ r, free, 1e2 * float(jnp.finfo(A.dtype).eps))
        r = r - Pr + jax.lax.stop_gradient(Pr)
        return r.astype(u_n.dtype), x

    def cost(self, u_n, args):
        """Reduced cost ``‖A x* + r0‖²`` (no extra render: the model is affine in ``x``)."""
        data, theta_ref = args
        theta = self.theta(u_n, theta_ref[self.idx_l], theta_ref)
        if not len(self.idx_l):
            return jnp.sum(self.residual(u_n, args)[0] ** 2)
        x, _, A, r0 = self.solve_linear(theta, data)
        return jnp.sum((A @ x + r0) ** 2)
