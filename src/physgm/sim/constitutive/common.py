"""Shared pieces of the constitutive models: the packed material struct, model ids, Hencky helpers.

Every model exposes two Warp functions with the same signature so one dispatch covers all:

    update(H_trial: mat33, mat: MaterialStruct, plastic: float, dt: float)
        -> (H_new: mat33, tau: mat33, plastic_new: float)
    energy(H: mat33, mat: MaterialStruct) -> float     # strain energy density, J/m^3

(the four Hencky-strain models share one energy, ``hencky_model_energy``).

H = F - I is the displacement gradient of the elastic deformation gradient F. Models work in H,
not F: a stiff material (E ~ 1e11 Pa) strains ~1e-5 per impact, and forming I + H in float32
rounds that strain to a few significant digits; the resulting stress noise (lam x 1e-7) made the
explicit step unstable. ``update`` applies the return mapping (if any) to the trial state and
returns the Kirchhoff stress tau = P F^T of the projected state, in Pa. ``plastic`` is one scalar
of history per particle (accumulated plastic strain for the hardening models).
"""

from __future__ import annotations

import warp as wp

from physgm.sim.linalg import rv_svd, sym_eig3

EYE = wp.constant(wp.mat33(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))

# Model ids used inside kernels. The name -> id table is ``constitutive.MODELS``.
FIXED_COROTATED = wp.constant(0)
NEO_HOOKEAN = wp.constant(1)
DRUCKER_PRAGER = wp.constant(2)
VON_MISES = wp.constant(3)
FOAM = wp.constant(4)
FLUID = wp.constant(5)
MOHR_COULOMB = wp.constant(6)

# Smallest principal stretch the Hencky models keep (log strain -6.9): inverted or collapsed
# trial states are projected to this barely-positive stretch instead of producing log(<=0).
SIGMA_MIN = wp.constant(1.0e-3)

# Largest elastic deviatoric Hencky strain ||dev eps|| the von Mises and foam return mappings
# keep. The StVK-Hencky energy mu ||eps||^2 + lam/2 tr(eps)^2 is not elliptic at large strain: its
# acoustic tensor turns indefinite from ||dev eps|| = 1.09 (nu = 0.01, tr eps = 0.3; 1.65-1.95 at
# nu = 0.49), measured over Lode angle, -2.3 <= tr eps <= 0.3 and nu in [0.01, 0.49]
# (docs/measurements_sim.md, section 9). There the material softens under a growing stretch and
# the grid localises it into an inversion at any time step, so a yield radius or a Perzyna
# overstress beyond this is returned to it rate-independently.
HENCKY_DEV_MAX = wp.constant(1.0)


@wp.struct
class MaterialStruct:
    """One material as the kernels see it (SI units). Unused fields are 0 for a model."""

    model: int  # model id (FIXED_COROTATED, ...)
    mu: float  # shear modulus, Pa
    lam: float  # first Lame parameter, Pa
    yield_stress: float  # von Mises / foam initial yield stress sigma_y, Pa
    hardening: float  # linear isotropic hardening modulus H, Pa
    alpha: float  # Drucker-Prager cone slope sqrt(2/3) 2 sin(phi) / (3 - sin(phi))
    tension_strain: float  # Drucker-Prager / Mohr-Coulomb apex in log volumetric strain (cohesion), >= 0
    viscosity: float  # foam Perzyna viscosity, Pa s
    bulk: float  # fluid bulk modulus, Pa
    sin_phi: float  # Mohr-Coulomb sin(friction angle)
    j_floor: float  # smallest det F of the elastic trial state a step may produce (divergence guard)


# A value the compiler must treat as unknown: the kernels compile with reassociation on the CPU
# (``physgm.warp_runtime.FAST_CPU_FLAGS``), under which clang folds (1 + x) - 1 to x and
# log(exp(x)) to x, which would undo the two tricks below (log1p(1e-6) then came out 4.6 % off;
# docs/measurements_sim.md section 18). An empty asm statement that may rewrite it keeps it as
# rounded. CUDA does not reassociate (Warp's default), so the value passes through there.
_OPAQUE = """
    float y = x;
#if !defined(__CUDA_ARCH__)
    __asm__ volatile("" : "+m"(y));
#endif
    return y;
"""


@wp.func_native(_OPAQUE)
def opaque(x: float) -> float: ...


@wp.func
def log1p(x: float) -> float:
    """log(1 + x), accurate for small x (Goldberg's trick on the rounded 1 + x)."""
    u = opaque(1.0 + x)
    if u == 1.0:
        return x
    return wp.log(u) * x / (u - 1.0)


@wp.func
def expm1(x: float) -> float:
    """exp(x) - 1, accurate for small x (Kahan's trick on the rounded exp(x))."""
    u = opaque(wp.exp(x))
    if u == 1.0:
        return x
    um1 = u - 1.0
    if um1 == -1.0:
        return -1.0
    return um1 * x / wp.log(u)


@wp.func
def det_minus_one(H: wp.mat33) -> float:
    """det(I + H) - 1 without the float32 cancellation of forming det(I + H) first."""
    minors = (
        (H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0])
        + (H[0, 0] * H[2, 2] - H[0, 2] * H[2, 0])
        + (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1])
    )
    return wp.trace(H) + minors + wp.determinant(H)


@wp.func
def green_minus_identity(H: wp.mat33) -> wp.mat33:
    """b - I = F F^T - I = H + H^T + H H^T, exact to float32 relative to the strain."""
    return H + wp.transpose(H) + H * wp.transpose(H)


@wp.func
def hencky_decompose(H: wp.mat33):
    """Eigenvectors U of b = F F^T, signed principal stretches and clamped Hencky strains.

    Decomposes b - I (small numbers, full relative precision) rather than b; eps_i =
    log1p(d_i) / 2. sigma[0] (the smallest stretch) carries the sign of det F. Returns (U, sigma,
    eps, clamped) where ``clamped`` says a stretch was below SIGMA_MIN (or inverted), so its strain
    is not log(sigma) and F must be rebuilt.
    """
    U, d = sym_eig3(green_minus_identity(H))
    sigma = wp.vec3(
        wp.sqrt(wp.max(1.0 + d[0], 0.0)), wp.sqrt(wp.max(1.0 + d[1], 0.0)), wp.sqrt(wp.max(1.0 + d[2], 0.0))
    )
    if det_minus_one(H) < -1.0:
        sigma[0] = -sigma[0]
    clamped = sigma[0] < SIGMA_MIN
    eps = wp.vec3(0.5 * log1p(d[0]), 0.5 * log1p(d[1]), 0.5 * log1p(d[2]))
    if clamped:
        eps[0] = wp.log(SIGMA_MIN)
        eps[1] = wp.log(wp.max(sigma[1], SIGMA_MIN))
        eps[2] = wp.log(wp.max(sigma[2], SIGMA_MIN))
    return U, sigma, eps, clamped


# Below this Frobenius norm of b - I, ``hencky_strain_series`` gives the Hencky strain to float32
# precision: the series' first omitted term is at most 0.05^6 / 12 = 1.3e-9, 5e-8 of the strain
# (float32's epsilon is 6e-8), and falls as the fifth power of the strain below it.
HENCKY_SERIES_MAX = wp.constant(0.05)


@wp.func
def hencky_strain_series(D: wp.mat33) -> wp.mat33:
    """Hencky strain eps = log(b) / 2 of b = I + D as a matrix, by the series of log(I + D) to
    D^5 (Horner form). No eigenvectors: the elastic steps of the Hencky models take it when
    ||D|| <= HENCKY_SERIES_MAX (strains up to ~2.5 %), where it agrees with ``hencky_decompose``
    to float32 round-off; the eigenvalues of eps are the principal strains."""
    L = (-1.0 / 4.0) * EYE + (1.0 / 5.0) * D
    L = (1.0 / 3.0) * EYE + D * L
    L = (-1.0 / 2.0) * EYE + D * L
    L = EYE + D * L
    return 0.5 * (D * L)


# Up to this Frobenius norm of b - I, ``hencky_strain_quadrature`` gives the Hencky strain to
# float32 precision: with every eigenvalue x of b - I in [-0.3, 0.3], its 4-point rule is off from
# log(1 + x) by at most 5.8e-9 of it (3-point: 7.2e-7; at 0.4, 4-point: 1.0e-7).
HENCKY_QUADRATURE_MAX = wp.constant(0.3)


@wp.func
def hencky_strain_quadrature(D: wp.mat33) -> wp.mat33:
    """Hencky strain eps = log(b) / 2 of b = I + D (D symmetric) as a matrix, by the 4-point
    Gauss-Legendre rule on log(I + D) = int_0^1 D (I + t D)^-1 dt (the [4/4] Pade approximant of
    the logarithm). No eigenvectors and no transcendental calls: the elastic steps of the Hencky
    models take it for HENCKY_SERIES_MAX < ||D|| <= HENCKY_QUADRATURE_MAX (strains up to ~15 %),
    at a quarter of ``hencky_decompose``'s cost (docs/measurements_sim.md section 35). Each term
    is D times a matrix near I, so the strain keeps D's relative precision."""
    s = 0.17392742256872679 * (D * wp.inverse(EYE + 0.06943184420297371 * D))
    s = s + 0.3260725774312732 * (D * wp.inverse(EYE + 0.33000947820757187 * D))
    s = s + 0.3260725774312732 * (D * wp.inverse(EYE + 0.6699905217924281 * D))
    s = s + 0.17392742256872679 * (D * wp.inverse(EYE + 0.9305681557970262 * D))
    return 0.5 * s


@wp.func
def hencky_small_strain(H: wp.mat33):
    """(True, eps as a matrix) when b - I of F = I + H is within HENCKY_QUADRATURE_MAX, else
    (False, 0): the Hencky models decide an elastic step on it (its invariants are the principal
    strains') and call ``hencky_decompose`` only for a large or yielding one. The series below
    HENCKY_SERIES_MAX (a body at rest), the quadrature above it (a body ringing after an impact)."""
    D = green_minus_identity(H)
    d2 = wp.ddot(D, D)
    if d2 <= HENCKY_SERIES_MAX * HENCKY_SERIES_MAX:
        return True, hencky_strain_series(D)
    if d2 <= HENCKY_QUADRATURE_MAX * HENCKY_QUADRATURE_MAX:
        return True, hencky_strain_quadrature(D)
    return False, wp.mat33(0.0)


@wp.func
def inverse_sqrt_minus_identity(D: wp.mat33) -> wp.mat33:
    """(I + D)^(-1/2) - I for a symmetric D with ||D|| <= HENCKY_SERIES_MAX, by the binomial series
    to D^6 (Horner form): its first omitted term, 429 / 2048 ||D||^7, is at most 6.5e-9 of the
    result's size (||D|| / 2) there."""
    S = (-63.0 / 256.0) * EYE + (231.0 / 1024.0) * D
    S = (35.0 / 128.0) * EYE + D * S
    S = (-5.0 / 16.0) * EYE + D * S
    S = (3.0 / 8.0) * EYE + D * S
    S = (-1.0 / 2.0) * EYE + D * S
    return D * S


@wp.func
def hencky_apex_return(H: wp.mat33, mat: MaterialStruct):
    """The granular models' return to the apex (the tension cut-off), without eigenvectors.

    A trial state whose volumetric strain tr eps = log J reaches ``tension_strain`` returns to the
    isotropic strain tension_strain / 3 (``drucker_prager_project``, ``mohr_coulomb_project``):
    F' = exp(tension_strain / 3) b^(-1/2) F, the rotation of F scaled, with b^(-1/2) from its
    series. Sand spreading at zero pressure sits there: 59-92 % of its particles every sub-step
    of the bench drop (docs/measurements_sim.md section 36). Returns (True, H', tau, the plastic
    multiplier) for a trial state within HENCKY_SERIES_MAX past the apex, else (False, ...): the
    caller takes the eigenvector path.
    """
    D = green_minus_identity(H)
    if wp.ddot(D, D) > HENCKY_SERIES_MAX * HENCKY_SERIES_MAX:
        return False, H, wp.mat33(0.0), 0.0
    eps = hencky_strain_series(D)
    tr = wp.trace(eps)  # log J
    if tr < mat.tension_strain:
        return False, H, wp.mat33(0.0), 0.0
    dev = eps - (tr / 3.0) * EYE
    dgamma = wp.sqrt(wp.ddot(dev, dev)) + tr - mat.tension_strain
    # F' - I = (1 + a) (I + S) F - I with a = exp(tension_strain / 3) - 1, S = b^(-1/2) - I:
    # H plus small terms, so H' keeps the relative precision of a stiff material's tiny strains.
    G = inverse_sqrt_minus_identity(D) * (EYE + H)
    a = expm1(mat.tension_strain / 3.0)
    H_new = H + G + a * (EYE + H + G)
    # The StVK-Hencky stress at eps = (tension_strain / 3) I.
    p = (2.0 * mat.mu + 3.0 * mat.lam) * mat.tension_strain / 3.0
    return True, H_new, wp.diag(wp.vec3(p)), dgamma


@wp.func
def hencky_stress(eps: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """StVK-Hencky Kirchhoff stress 2 mu eps + lam tr(eps) I of a strain given as a matrix, Pa."""
    return 2.0 * mu * eps + (lam * wp.trace(eps)) * EYE


@wp.func
def hencky_finish(
    H: wp.mat33,
    U: wp.mat33,
    sigma: wp.vec3,
    eps_old: wp.vec3,
    eps: wp.vec3,
    rebuild: bool,
    clamped: bool,
    mu: float,
    lam: float,
):
    """Projected displacement gradient and StVK-Hencky Kirchhoff stress U diag(2 mu eps + lam tr eps) U^T.

    F = U diag(sigma) V^T, so the state with strains ``eps`` is F' = U diag(exp(eps) / sigma) U^T F
    and H' = H + U diag(exp(eps) / sigma - 1) U^T F, with exp(eps) / sigma - 1 = expm1(eps -
    eps_old) whenever eps_old = log(sigma) is exact: no right singular vectors, no cancellation.
    """
    tr = eps[0] + eps[1] + eps[2]
    tau = U * wp.diag(2.0 * mu * eps + wp.vec3(lam * tr)) * wp.transpose(U)
    if not rebuild:
        return H, tau
    if not clamped:
        r = wp.vec3(expm1(eps[0] - eps_old[0]), expm1(eps[1] - eps_old[1]), expm1(eps[2] - eps_old[2]))
        return H + U * wp.diag(r) * (wp.transpose(U) * (EYE + H)), tau
    if wp.abs(sigma[0]) > 1.0e-6:
        r = wp.vec3(
            wp.exp(eps[0]) / sigma[0] - 1.0, wp.exp(eps[1]) / sigma[1] - 1.0, wp.exp(eps[2]) / sigma[2] - 1.0
        )
        return H + U * wp.diag(r) * (wp.transpose(U) * (EYE + H)), tau
    Us, s, V = rv_svd(EYE + H)
    return Us * wp.diag(wp.vec3(wp.exp(eps[0]), wp.exp(eps[1]), wp.exp(eps[2]))) * wp.transpose(V) - EYE, tau


@wp.func
def hencky_energy(eps: wp.vec3, mu: float, lam: float) -> float:
    tr = eps[0] + eps[1] + eps[2]
    return mu * wp.dot(eps, eps) + 0.5 * lam * tr * tr


@wp.func
def hencky_model_energy(H: wp.mat33, mat: MaterialStruct) -> float:
    """The ``energy`` of every Hencky-strain model (Drucker-Prager, Mohr-Coulomb, von Mises, foam):
    their return maps differ, but the elastic energy of a state is StVK-Hencky's for all four."""
    U, sigma, eps, clamped = hencky_decompose(H)
    return hencky_energy(eps, mat.mu, mat.lam)
