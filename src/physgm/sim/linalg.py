"""Small dense 3x3 linear algebra inside Warp kernels (eigen, rotation-variant SVD, stretch).

``wp.svd3`` and ``wp.eig3`` cost ~300 ns per call on this CPU and lose ~1e-3 of accuracy on
general matrices, more than the whole MPM transfer. Every constitutive model here is isotropic,
so it only needs the eigen-decomposition of the symmetric left Cauchy-Green tensor
b = F F^T = U diag(sigma^2) U^T. ``sym_eig3`` is a non-iterative solver (trigonometric
eigenvalues, eigenvectors from cross products of the rows of b - beta I, the middle one from a
2x2 problem in the orthogonal complement; the construction of D. Eberly, "A robust eigensolver
for 3x3 symmetric matrices", 2014). It is robust to repeated eigenvalues, which is the common
case here (b ~ I at rest). The numpy twin is ``constitutive.reference``.
"""

from __future__ import annotations

import math

import warp as wp

_TWO_PI_3 = 2.0 * math.pi / 3.0
FLOAT32_MAX = wp.constant(3.4028234663852886e38)


@wp.func
def is_finite(x: float) -> bool:
    """Neither inf nor NaN (NaN fails every comparison). ``wp.isfinite`` asks the same through
    a call into Warp's runtime library on the CPU, which costs g2p a few percent."""
    return wp.abs(x) <= FLOAT32_MAX


@wp.func
def _unit_eigenvector_from_rows(b: wp.mat33, beta: float) -> wp.vec3:
    """Eigenvector of symmetric ``b`` for an eigenvalue ``beta`` of multiplicity one."""
    r0 = wp.vec3(b[0, 0] - beta, b[0, 1], b[0, 2])
    r1 = wp.vec3(b[0, 1], b[1, 1] - beta, b[1, 2])
    r2 = wp.vec3(b[0, 2], b[1, 2], b[2, 2] - beta)
    c01 = wp.cross(r0, r1)
    c02 = wp.cross(r0, r2)
    c12 = wp.cross(r1, r2)
    d01 = wp.dot(c01, c01)
    d02 = wp.dot(c02, c02)
    d12 = wp.dot(c12, c12)
    # The largest cross product is the best conditioned null-space direction.
    best = c01
    dmax = d01
    if d02 > dmax:
        best = c02
        dmax = d02
    if d12 > dmax:
        best = c12
        dmax = d12
    if dmax <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    return best / wp.sqrt(dmax)


@wp.func
def _orthogonal_complement(w: wp.vec3) -> wp.mat33:
    """Rows 0 and 1: an orthonormal pair (u, v) perpendicular to unit ``w``."""
    u = wp.vec3(0.0)
    if wp.abs(w[0]) > wp.abs(w[1]):
        s = 1.0 / wp.sqrt(w[0] * w[0] + w[2] * w[2])
        u = wp.vec3(-w[2] * s, 0.0, w[0] * s)
    else:
        s = 1.0 / wp.sqrt(w[1] * w[1] + w[2] * w[2])
        u = wp.vec3(0.0, w[2] * s, -w[1] * s)
    v = wp.cross(w, u)
    return wp.mat33(u[0], u[1], u[2], v[0], v[1], v[2], 0.0, 0.0, 0.0)


@wp.func
def sym_eig3(b: wp.mat33):
    """Eigen-decomposition b = Q diag(beta) Q^T of a symmetric 3x3 matrix.

    Returns:
        Q: right-handed orthonormal eigenvectors as columns (det = +1).
        beta: eigenvalues in ascending order.
    """
    q = (b[0, 0] + b[1, 1] + b[2, 2]) / 3.0
    c00 = b[0, 0] - q
    c11 = b[1, 1] - q
    c22 = b[2, 2] - q
    off = b[0, 1] * b[0, 1] + b[0, 2] * b[0, 2] + b[1, 2] * b[1, 2]
    p2 = (c00 * c00 + c11 * c11 + c22 * c22 + 2.0 * off) / 6.0
    if p2 <= 1.0e-28 * q * q:
        return wp.identity(n=3, dtype=float), wp.vec3(b[0, 0], b[1, 1], b[2, 2])
    p = wp.sqrt(p2)
    ip = 1.0 / p
    n00 = c00 * ip
    n11 = c11 * ip
    n22 = c22 * ip
    n01 = b[0, 1] * ip
    n02 = b[0, 2] * ip
    n12 = b[1, 2] * ip
    half_det = 0.5 * (
        n00 * (n11 * n22 - n12 * n12) - n01 * (n01 * n22 - n12 * n02) + n02 * (n01 * n12 - n11 * n02)
    )
    phi = wp.acos(wp.clamp(half_det, -1.0, 1.0)) / 3.0
    # The trigonometric root farthest from the other two is accurate even in float32; the
    # close pair is not (acos is ill-conditioned there), so it is re-solved below as a 2x2
    # problem in the plane perpendicular to the far eigenvector.
    top_is_far = half_det >= 0.0
    beta_far = q + 2.0 * p * wp.cos(phi + _TWO_PI_3)
    if top_is_far:
        beta_far = q + 2.0 * p * wp.cos(phi)
    e_far = _unit_eigenvector_from_rows(b, beta_far)
    uv = _orthogonal_complement(e_far)
    u = wp.vec3(uv[0, 0], uv[0, 1], uv[0, 2])
    v = wp.vec3(uv[1, 0], uv[1, 1], uv[1, 2])
    bu = b * u
    bv = b * v
    m00 = wp.dot(u, bu)
    m01 = wp.dot(u, bv)
    m11 = wp.dot(v, bv)
    # One Jacobi rotation diagonalises the 2x2 block exactly.
    la = m00
    lb = m11
    ea = u
    eb = v
    if m01 != 0.0:
        theta = (m11 - m00) / (2.0 * m01)
        t = 1.0 / (wp.abs(theta) + wp.sqrt(theta * theta + 1.0))
        if theta < 0.0:
            t = -t
        cs = 1.0 / wp.sqrt(t * t + 1.0)
        sn = t * cs
        la = m00 - t * m01
        lb = m11 + t * m01
        ea = cs * u - sn * v
        eb = sn * u + cs * v
    if la > lb:
        tmp = la
        la = lb
        lb = tmp
        tv = ea
        ea = eb
        eb = tv
    beta_far = wp.dot(e_far, b * e_far)
    if top_is_far:
        return wp.matrix_from_cols(ea, eb, wp.cross(ea, eb)), wp.vec3(la, lb, beta_far)
    return wp.matrix_from_cols(e_far, ea, wp.cross(e_far, ea)), wp.vec3(beta_far, la, lb)


@wp.func
def rv_svd(F: wp.mat33):
    """Rotation-variant SVD F = U diag(sigma) V^T with det U = det V = +1.

    Built on ``sym_eig3(F F^T)``: sigma is ascending in magnitude and sigma[0] carries the
    sign of det F, so an inverted F has sigma[0] < 0 (Irving et al. 2004 convention).
    """
    U, beta = sym_eig3(F * wp.transpose(F))
    W = wp.transpose(F) * U  # column i = F^T u_i = sigma_i v_i
    w1 = wp.vec3(W[0, 1], W[1, 1], W[2, 1])
    w2 = wp.vec3(W[0, 2], W[1, 2], W[2, 2])
    s2 = wp.length(w2)
    if s2 <= 1.0e-30:
        return U, wp.vec3(0.0), U
    v2 = w2 / s2
    w1 = w1 - wp.dot(w1, v2) * v2
    s1 = wp.length(w1)
    v1 = wp.vec3(0.0)
    if s1 > 1.0e-30:
        v1 = w1 / s1
    else:
        # Rank one: any unit vector perpendicular to v2 completes the basis.
        uv = _orthogonal_complement(v2)
        v1 = wp.vec3(uv[0, 0], uv[0, 1], uv[0, 2])
    v0 = wp.cross(v1, v2)
    s0 = wp.dot(wp.vec3(W[0, 0], W[1, 0], W[2, 0]), v0)
    return U, wp.vec3(s0, s1, s2), wp.matrix_from_cols(v0, v1, v2)


@wp.func
def left_stretch_minus_identity(D: wp.mat33, e: float) -> wp.mat33:
    """V - I for the left stretch V = sqrt(b), from D = b - I and e = det F - 1 (det F > 0).

    Cayley-Hamilton closed form V = ((i1^2 - i2) b - b^2 + i1 i3 I) / (i1 i2 - i3) (Hoger and
    Carlson 1984), with the invariants of V written as deviations from the identity's,
    i1 = 3 + a, i2 = 3 + c, i3 = 1 + e, so nothing of size 1 cancels in float32: with T = tr D,
    c = 3 a + a^2 / 2 - T / 2 and a is the root of
        f(a) = 16 a + 3 a^2 - 5 T + u^2 / 4 - 6 e - 2 a e - (T^2 - tr D^2) / 2,  u = 6 a + a^2 - T,
    reached by Newton's method from the upper bound a0 = sqrt(9 + 3 T) - 3 (f is convex and
    increasing above the root, so the iteration descends monotonically; a0 is exact for D = 0).
    Then V - I = (k0 I + k1 D - D^2) / d with k0 = (4 + a)(a + e - c), k1 = 4 + 6 a + a^2 - c,
    d = 8 + 3 a + 3 c + a c - e. No eigenvalues, no trigonometry. Returns a matrix with a NaN
    when d (= (s0+s1)(s1+s2)(s0+s2) in stretches) is too small; callers then use ``rv_svd``.
    """
    T = wp.trace(D)
    D2 = D * D
    q = 0.5 * (T * T - wp.trace(D2))
    a = 3.0 * T / (wp.sqrt(wp.max(9.0 + 3.0 * T, 0.0)) + 3.0)
    for _ in range(12):
        u = 6.0 * a + a * a - T
        f = 16.0 * a + 3.0 * a * a - 5.0 * T + 0.25 * u * u - 6.0 * e - 2.0 * a * e - q
        df = 16.0 + 6.0 * a + u * (3.0 + a) - 2.0 * e
        if df <= 0.0:
            break
        step = f / df
        a = a - step
        # Newton converges quadratically: the error left is about step^2 f'' / (2 f'), so stop
        # when that is below 1e-7 |a| rather than taking one more step only to see it is small
        # (usually saves one of two iterations, ~13 ns of the ~40).
        curvature = 6.0 + 0.5 * (6.0 + 2.0 * a) * (6.0 + 2.0 * a) + u
        if step * step * curvature <= 2.0e-7 * df * wp.abs(a):
            break
    c = 3.0 * a + 0.5 * a * a - 0.5 * T
    d = 8.0 + 3.0 * a + 3.0 * c + a * c - e
    s = 3.0 + a
    if not (d > 1.0e-6 * s * s * s):
        return wp.mat33(wp.nan)
    k0 = (4.0 + a) * (a + e - c)
    k1 = 4.0 + 6.0 * a + a * a - c
    return (wp.diag(wp.vec3(k0)) + k1 * D - D2) * (1.0 / d)  # one division, not nine
