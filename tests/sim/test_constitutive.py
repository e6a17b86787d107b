"""Warp constitutive models against their numpy twins (stress, return mapping, energy)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from physgm.sim.constitutive import MODELS, MaterialParams
from physgm.sim.constitutive import reference as ref
from physgm.sim.constitutive.common import expm1, log1p
from physgm.sim.linalg import is_finite
from physgm.warp_runtime import FAST_CPU_FLAGS
from tests.sim.constitutive_runs import DT, run_warp

# The kernels below compile as the solver's do (reassociation on the CPU).
wp.set_module_options({"enable_backward": False, "cpu_compiler_flags": FAST_CPU_FLAGS})

PARAMS = {
    "fixed_corotated": MaterialParams("fixed_corotated", 1.0e6, 0.3, 1000.0),
    "neo_hookean": MaterialParams("neo_hookean", 1.0e6, 0.45, 1000.0),
    "drucker_prager": MaterialParams(
        "drucker_prager", 1.0e6, 0.3, 1600.0, friction_angle=30.0, cohesion=2.0e3
    ),
    "mohr_coulomb": MaterialParams("mohr_coulomb", 1.0e6, 0.3, 1600.0, friction_angle=30.0, cohesion=2.0e3),
    "von_mises": MaterialParams("von_mises", 1.0e6, 0.3, 1500.0, yield_stress=2.0e4, hardening=1.0e5),
    "foam": MaterialParams("foam", 1.0e6, 0.2, 100.0, yield_stress=2.0e4, hardening=1.0e4, viscosity=10.0),
    "fluid": MaterialParams("fluid", 1.0e6, 0.3, 1000.0),
}


def random_F(n: int, seed: int) -> np.ndarray:
    """Near-identity, large, rotated and inverted deformation gradients, [n, 3, 3]."""
    rng = np.random.default_rng(seed)
    small = np.eye(3) + 1e-3 * rng.standard_normal((n, 3, 3))
    large = np.eye(3) + 0.3 * rng.standard_normal((n, 3, 3))
    q, _ = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    q *= np.sign(np.linalg.det(q))[:, None, None]
    stretch = np.einsum("nij,nj,nkj->nik", q, rng.uniform(0.5, 1.6, (n, 3)), q)
    rotated = q @ stretch
    inverted = large.copy()
    inverted[:, :, 0] *= -1  # mirror: det < 0
    F = np.concatenate([small, large, rotated, inverted])
    return F[np.abs(np.linalg.det(F)) > 0.05]  # keep away from exactly singular matrices


def test_registry_covers_every_model_with_a_twin():
    assert set(MODELS) == set(PARAMS)
    assert sorted(m.id for m in MODELS.values()) == list(range(len(MODELS)))


@pytest.mark.parametrize("model", list(PARAMS))
def test_stress_and_return_mapping_match_numpy(model):
    p = PARAMS[model]
    F = random_F(200, seed=1)
    # Reference in float64 on the float32-rounded input the kernel sees.
    F = F.astype(np.float32).astype(np.float64)
    plastic = np.zeros(len(F))
    got = run_warp(p, F, plastic)
    F_ref, tau_ref, pl_ref = ref.update(p, F, plastic, DT)
    scale = p.lam + 2 * p.mu
    # float32 kernel vs float64 twin: error relative to the stress scale and to the stress itself
    bound = scale * (1 + np.abs(F).max(axis=(1, 2)) ** 2) + 20 * np.abs(tau_ref).max(axis=(1, 2))
    tau_err = np.abs(got["tau"] - tau_ref).max(axis=(1, 2)) / bound
    assert tau_err.max() < 5e-5, f"{model}: worst stress error {tau_err.max():.3g} at F={F[tau_err.argmax()]}"
    np.testing.assert_allclose(got["F"], F_ref, atol=5e-5 * (1 + np.abs(F_ref).max()))
    if pl_ref is not None:
        np.testing.assert_allclose(got["plastic"], pl_ref, rtol=1e-3, atol=1e-5)
    e_ref = ref.energy_density(model, F, p.mu, p.lam, p.bulk)
    np.testing.assert_allclose(got["energy"], e_ref, rtol=1e-3, atol=2e-6 * scale)


@pytest.mark.parametrize("model", ["fixed_corotated", "neo_hookean", "fluid"])
def test_reference_stress_is_the_energy_gradient(model):
    """tau = (d psi / d F) F^T: checks the twin itself by central differences, inverted F included."""
    p = PARAMS[model]
    F = random_F(20, seed=2)
    if model == "fluid":  # the fluid clamps J below J_MIN_FLUID, where it is not hyperelastic
        F = F[np.linalg.det(F) > 2 * ref.J_MIN_FLUID]
    if model in ("fixed_corotated", "neo_hookean"):  # their volume barriers are defined for J > 0 only
        F = F[np.linalg.det(F) > 0.01]
        if model == "fixed_corotated":
            assert (np.linalg.det(F) < ref.FC_J_B).sum() >= 3  # the barrier branch is exercised
    _, tau, _ = ref.update(p, F, np.zeros(len(F)), DT)
    h = 1e-6
    P = np.zeros_like(F)
    for i in range(3):
        for j in range(3):
            dF = np.zeros((3, 3))
            dF[i, j] = h
            P[:, i, j] = (
                ref.energy_density(model, F + dF, p.mu, p.lam, p.bulk)
                - ref.energy_density(model, F - dF, p.mu, p.lam, p.bulk)
            ) / (2 * h)
    np.testing.assert_allclose(P @ np.swapaxes(F, 1, 2), tau, rtol=1e-5, atol=1e-5 * p.E)


def test_hencky_stress_is_the_energy_gradient_inside_the_yield_surface():
    p = MaterialParams("von_mises", 1.0e6, 0.3, 1000.0, yield_stress=1.0e12)  # yields only at the cap
    F = random_F(20, seed=3)
    F = F[np.linalg.det(F) > 0.1]
    F = F[deviatoric_strain(F) < ref.HENCKY_DEV_MAX]
    assert len(F) > 30
    _, tau, _ = ref.update(p, F, np.zeros(len(F)), DT)
    h = 1e-6
    P = np.zeros_like(F)
    for i in range(3):
        for j in range(3):
            dF = np.zeros((3, 3))
            dF[i, j] = h
            P[:, i, j] = (
                ref.energy_density("von_mises", F + dF, p.mu, p.lam)
                - ref.energy_density("von_mises", F - dF, p.mu, p.lam)
            ) / (2 * h)
    np.testing.assert_allclose(P @ np.swapaxes(F, 1, 2), tau, rtol=1e-5, atol=1e-5 * p.E)


def deviatoric_strain(F: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N], ||dev log stretch||
    eps = np.log(np.abs(np.linalg.svd(F, compute_uv=False)))
    return np.linalg.norm(eps - eps.mean(1, keepdims=True), axis=1)


def min_acoustic_eigenvalue(params: MaterialParams, stretch: np.ndarray, normals: np.ndarray) -> float:
    """Smallest eigenvalue of the acoustic tensor of the elastic Hencky law at F = diag(stretch), Pa."""
    huge = dataclasses.replace(params, yield_stress=1e30 * params.E, viscosity=0.0)

    def first_pk(F):  # [3, 3] -> [3, 3]; the numpy twin without the cap (radius far above it)
        U, Vt, eps = ref._hencky(F[None])
        _, tau = ref._hencky_out(U, Vt, eps, huge.mu, huge.lam)
        return tau[0] @ np.linalg.inv(F).T

    F, h = np.diag(stretch), 1e-6
    A = np.zeros((3, 3, 3, 3))  # dP_iJ / dF_kL
    for k in range(3):
        for L in range(3):
            dF = np.zeros((3, 3))
            dF[k, L] = h * stretch[L]
            A[:, :, k, L] = (first_pk(F + dF) - first_pk(F - dF)) / (2 * dF[k, L])
    Q = np.einsum("iJkL,nJ,nL->nik", A, normals, normals)
    return float(np.linalg.eigvalsh(Q)[:, 0].min())


@pytest.mark.parametrize("nu", [0.01, 0.49])
def test_hencky_energy_is_elliptic_up_to_the_cap_and_not_beyond(nu):
    """HENCKY_DEV_MAX lies inside the region where the Hencky law's acoustic tensor is positive."""
    p = MaterialParams("von_mises", 1.0e6, nu, 1000.0, yield_stress=1.0e3)
    rng = np.random.default_rng(0)
    normals = rng.standard_normal((800, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    e1, e2 = np.array([2.0, -1.0, -1.0]) / np.sqrt(6), np.array([0.0, 1.0, -1.0]) / np.sqrt(2)
    for tr in (-2.3, 0.0, 0.5):
        for lode in np.linspace(0.0, np.pi / 3, 4):
            direction = np.cos(lode) * e1 + np.sin(lode) * e2
            at_cap = np.exp(tr / 3 + ref.HENCKY_DEV_MAX * direction)
            assert min_acoustic_eigenvalue(p, at_cap, normals) > 0.0, (tr, lode)
    # and beyond 2.0 it is not (so the cap is not an arbitrary stiffness limit)
    assert min_acoustic_eigenvalue(p, np.exp(2.0 * e2), normals) < 0.0


@pytest.mark.parametrize("model", ["von_mises", "foam"])
def test_elastic_strain_is_returned_to_the_hencky_cap(model):
    """Yield radius or Perzyna overstress far above the cap: the elastic strain still ends on it."""
    extra = dict(yield_stress=1.0e9) if model == "von_mises" else dict(yield_stress=1.0e4, viscosity=1.0e9)
    p = MaterialParams(model, 1.0e6, 0.49, 1000.0, **extra)
    F = np.stack([np.diag([a, 1.0, 1.0 / a]) for a in (1.5, 3.0, 30.0)])  # ||dev|| 0.57, 1.55, 4.8
    got = run_warp(p, F, np.zeros(len(F)))
    dev = deviatoric_strain(got["F"])
    np.testing.assert_allclose(dev[1:], ref.HENCKY_DEV_MAX, rtol=1e-4)
    np.testing.assert_allclose(np.linalg.det(got["F"]), 1.0, rtol=1e-4)  # the volume is kept
    if model == "von_mises":
        np.testing.assert_allclose(got["F"][0], F[0], atol=1e-6)  # inside: untouched
    _, tau_ref, kappa_ref = ref.update(p, F, np.zeros(len(F)), DT)
    # float32 log strains of a 30-fold stretch: the volumetric stress lam tr(eps) to ~1e-5 lam
    np.testing.assert_allclose(got["tau"], tau_ref, rtol=1e-4, atol=1e-3 * p.mu)
    np.testing.assert_allclose(got["plastic"], kappa_ref, rtol=1e-4, atol=1e-7)


def test_projected_states_lie_on_or_inside_the_yield_surface():
    F = random_F(200, seed=4)
    for model in ("drucker_prager", "von_mises"):
        p = PARAMS[model]
        got = run_warp(p, F, np.zeros(len(F)))
        _, s, _ = ref.rv_svd(got["F"])
        eps = np.log(np.maximum(s, ref.SIGMA_MIN))
        tr = eps.sum(1)
        dev = np.linalg.norm(eps - tr[:, None] / 3, axis=1)
        if model == "von_mises":
            radius = np.sqrt(2 / 3) * (p.yield_stress + p.hardening * got["plastic"]) / (2 * p.mu)
            assert np.all(dev <= radius * (1 + 1e-3) + 1e-6)
            assert (got["plastic"] > 0).sum() > len(F) // 4  # the test F really do yield
        else:
            s_ = p.pack()
            f = dev + s_.alpha * (3 * p.lam + 2 * p.mu) / (2 * p.mu) * (tr - s_.tension_strain)
            tol = 3e-5 * (1 + np.abs(eps).sum(1))  # float32 rounding of log strains (up to |eps| ~ 3.4 here)
            assert np.all(f <= tol) and np.all(tr <= s_.tension_strain + tol)
        # Elastic, non-inverted states stay untouched (inverted ones are projected to SIGMA_MIN).
        inside = (got["plastic"] == 0) & (np.linalg.det(F) > 0)
        np.testing.assert_allclose(got["F"][inside], F[inside], atol=1e-5)


def test_foam_relaxes_between_elastic_and_rate_independent():
    F = np.tile(np.diag([1.2, 1 / 1.2, 1.0]), (1, 1, 1))
    kappa = {}
    for eta in (0.0, 10.0, 1e9):
        p = MaterialParams("foam", 1.0e6, 0.2, 100.0, yield_stress=1.0e4, viscosity=eta)
        kappa[eta] = run_warp(p, F, np.zeros(1))["plastic"][0]
    assert kappa[0.0] > kappa[10.0] > kappa[1e9] >= 0
    assert kappa[1e9] < 1e-6 * kappa[0.0]


def test_neo_hookean_is_finite_and_restoring_when_inverted():
    p = PARAMS["neo_hookean"]
    J = np.array([0.5, 0.1, 0.05, 0.0, -0.05, -0.3])
    F = np.cbrt(np.abs(J))[:, None, None] * np.eye(3)
    F[:, 2, 2] *= np.where(J < 0, -1, 1)
    F[3] = np.diag([1.0, 1.0, 0.0])
    got = run_warp(p, F, np.zeros(len(F)))
    P = ref.neo_hookean_first_pk(F, p.mu, p.lam)
    assert np.all(np.isfinite(got["tau"])) and np.all(np.isfinite(P))
    # Energy grows monotonically as the volume collapses and inverts.
    e = ref.energy_density("neo_hookean", F, p.mu, p.lam)
    assert np.all(np.diff(e) > 0)


def test_fluid_resets_F_to_isotropic():
    F = random_F(50, seed=5)
    got = run_warp(PARAMS["fluid"], F, np.zeros(len(F)))
    J = np.maximum(np.linalg.det(F), ref.J_MIN_FLUID)
    np.testing.assert_allclose(got["F"], np.cbrt(J)[:, None, None] * np.eye(3), rtol=2e-5, atol=2e-6)


def test_fluid_pushes_back_harder_the_more_it_is_compressed():
    """tau = K (J - 1): before, tau = K (J - 1) J peaked at K / 4 at J = 1/2 and fell to 0 at J -> 0."""
    p = PARAMS["fluid"]
    J = np.array([0.9, 0.5, 0.3, 0.1, 0.06])
    got = run_warp(p, np.cbrt(J)[:, None, None] * np.eye(3), np.zeros(len(J)))
    pressure = -np.trace(got["tau"], axis1=1, axis2=2) / 3  # Kirchhoff, Pa (positive: pushes out)
    assert np.all(np.diff(pressure) > 0)
    np.testing.assert_allclose(pressure, p.bulk * (1 - J), rtol=1e-5)


def test_fixed_corotated_volume_barrier_pushes_back_and_is_c1():
    """Below J = 1/2 the pressure keeps growing in compression (Stomakhin's returns to 0 at J = 0)."""
    lam = 1.0
    J = np.array([0.9, 0.5 + 1e-7, 0.5 - 1e-7, 0.3, 0.1, 0.01, 1e-4])
    p = ref.fc_volume_pressure(J, lam, lam)
    assert p[1] == pytest.approx(p[2], abs=1e-6) and p[1] == pytest.approx(-0.25, abs=1e-6)
    assert np.all(np.diff(p[2:]) < 0)  # more compression, more (negative) pressure
    assert p[-2] < -4 * lam  # J = 1 % pushes back with over 4 lam (Stomakhin: -0.0099 lam)
    e = ref.fc_volume_energy(J, lam, lam)
    assert np.all(np.diff(e[2:]) > 0) and e[-1] > 10 * lam  # a barrier: unbounded as J -> 0


def principal_stress(tau: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3] descending
    return np.linalg.eigvalsh(0.5 * (tau + np.swapaxes(tau, 1, 2)))[:, ::-1]


def test_mohr_coulomb_states_lie_on_or_inside_the_hexagon_at_their_volume():
    p = PARAMS["mohr_coulomb"]
    F = random_F(200, seed=4)
    got = run_warp(p, F, np.zeros(len(F)))
    t1, _, t3 = principal_stress(got["tau"]).T
    s, c = np.sin(np.radians(30.0)), 2.0e3
    f = (t1 - t3) + (t1 + t3) * s - 2 * c * np.cos(np.radians(30.0))
    assert np.all(f <= 1e-4 * p.E)
    assert (got["plastic"] > 0).sum() > len(F) // 4  # the test F really do yield
    # The flow is deviatoric: J is kept below the apex (non-inverted states).
    yielded = (got["plastic"] > 0) & (np.linalg.det(F) > 0.2)
    J0, J1 = np.linalg.det(F[yielded]), np.linalg.det(got["F"][yielded])
    below_apex = np.log(J0) < 3 * c / np.tan(np.radians(30.0)) / (3 * p.lam + 2 * p.mu)
    np.testing.assert_allclose(J1[below_apex], J0[below_apex], rtol=2e-4)


@pytest.mark.parametrize("model", ["mohr_coulomb", "drucker_prager"])
def test_plane_shear_strength_of_the_granular_models(model):
    """Pure shear in the xz plane at fixed volume (plane strain): the friction a flow feels.

    Mohr-Coulomb holds max shear / pressure = sin(phi); the Drucker-Prager cone matched at
    triaxial compression holds 6 sin(phi) / (sqrt(3) (3 - sin(phi))), 0.82 instead of 0.57 at
    phi = 35 degrees (the reason sand uses mohr_coulomb).
    """
    p = MaterialParams(model, 1.0e6, 0.3, 1600.0, friction_angle=35.0)
    press = 0.01  # compressive volumetric log strain / 3 on each axis
    gammas = np.linspace(0.0, 0.05, 11)
    F = np.stack([np.diag([np.exp(-press + g), np.exp(-press), np.exp(-press - g)]) for g in gammas])
    got = run_warp(p, F, np.zeros(len(F)))
    t = principal_stress(got["tau"])
    ratio = ((t[:, 0] - t[:, 2]) / 2 / (-t.mean(1)))[-1]
    s = np.sin(np.radians(35.0))
    expected = s if model == "mohr_coulomb" else 6 * s / (np.sqrt(3) * (3 - s))
    assert ratio == pytest.approx(expected, rel=2e-3)


@pytest.mark.parametrize("model", ["fixed_corotated", "neo_hookean"])
def test_volume_barrier_holds_when_lam_vanishes(model):
    """At nu = 0.01 lam is 2 % of mu: a barrier scaled by lam alone (fixed_corotated before) or none
    below J_E (neo_hookean before) left a crushed particle at |p| < mu, and a cube hit at twice its
    wave speed inverted. The barrier on lam + 2 mu pushes back with several mu."""
    p = MaterialParams(model, 1e4, 0.01, 1000.0)
    J = np.array([0.2, 0.05, 0.01, 1e-3])
    F = np.cbrt(J)[:, None, None] * np.eye(3)
    got = run_warp(p, F, np.zeros(len(F)))
    pressure = np.trace(got["tau"], axis1=1, axis2=2) / 3  # Kirchhoff, Pa (negative: pushes out)
    assert np.all(np.diff(pressure) < 0)
    assert pressure[2] < -5 * p.mu, pressure / p.mu
    _, tau_ref, _ = ref.update(p, F, np.zeros(len(F)), DT)
    np.testing.assert_allclose(got["tau"], tau_ref, rtol=1e-4, atol=1e-3 * p.mu)


# ||b - I|| of the Hencky models' two paths without eigenvectors: the series, then the quadrature.
STRAIN_PATHS = {"series": (0.0, 0.05), "quadrature": (0.05, 0.3)}


@pytest.mark.parametrize("model", ["von_mises", "foam", "drucker_prager"])
@pytest.mark.parametrize("rotated", [False, True])
@pytest.mark.parametrize("path", list(STRAIN_PATHS))
def test_small_elastic_strains_match_numpy_to_float32_precision(model, rotated, path):
    """Below HENCKY_QUADRATURE_MAX the Hencky models take the strain's series (up to ||b - I|| =
    0.05) or its quadrature (up to 0.3) instead of its eigenvectors: the stress must still be the
    twin's, relative to itself, up to the edge of each. A pure stretch from 1e-6 strain (F - I is
    exact in float32 there); a rotated one from 1e-3, since rounding the rotated F to float32
    costs b - I ~1e-7 absolute. Elastic throughout: von Mises and foam with a high yield stress,
    Drucker-Prager compressed inside its cone (the deviatoric part a fifth of the volumetric one)."""
    rng = np.random.default_rng(7)
    granular = model == "drucker_prager"
    p = PARAMS[model] if granular else dataclasses.replace(PARAMS[model], yield_stress=1e9)
    n = 400
    sym = rng.standard_normal((n, 3, 3))
    sym = 0.5 * (sym + sym.transpose(0, 2, 1))
    if granular:
        dev = sym - np.trace(sym, axis1=1, axis2=2)[:, None, None] / 3 * np.eye(3)
        sym = -np.eye(3) + 0.2 * dev / np.linalg.norm(dev, axis=(1, 2))[:, None, None]
    lo, hi = STRAIN_PATHS[path]
    # strain ~ ||b - I|| / 2
    size = (
        10.0 ** rng.uniform(-3 if rotated else -6, np.log10(0.024), n)
        if lo == 0.0
        else rng.uniform(0.026, 0.138, n)
    )
    F = np.eye(3) + sym * (size / np.linalg.norm(sym, axis=(1, 2)))[:, None, None]
    if rotated:
        q, _ = np.linalg.qr(rng.standard_normal((n, 3, 3)))
        F = q * np.sign(np.linalg.det(q))[:, None, None] @ F
    F = F.astype(np.float32).astype(np.float64)
    norm = np.linalg.norm(F @ F.transpose(0, 2, 1) - np.eye(3), axis=(1, 2))
    assert ((lo < norm) & (norm < hi)).all()  # every state on the path
    got = run_warp(p, F, np.zeros(n))
    _, tau_ref, _ = ref.update(p, F, np.zeros(n), DT)
    err = np.abs(got["tau"] - tau_ref).max(axis=(1, 2)) / np.abs(tau_ref).max(axis=(1, 2))
    assert err.max() < (1e-3 if rotated else 2e-5), (np.median(err), err.max())
    # Elastic: H untouched; F - I + I in float32 rounds a rotated F's entries by up to an ulp.
    np.testing.assert_allclose(got["F"], F, rtol=0, atol=2.5e-7)


@pytest.mark.parametrize("model", ["drucker_prager", "mohr_coulomb"])
@pytest.mark.parametrize("path", list(STRAIN_PATHS))
def test_small_strains_on_both_sides_of_the_granular_yield_surface_match_numpy(model, path):
    """Drucker-Prager's paths without eigenvectors decide elastic from invariants: a strain just
    outside the cone must still be returned as the twin returns it (Mohr-Coulomb, always on the
    eigen path, as the control)."""
    rng = np.random.default_rng(11)
    p = PARAMS[model]
    n = 600
    sym = rng.standard_normal((n, 3, 3))
    sym = 0.5 * (sym + sym.transpose(0, 2, 1))
    dev = sym - np.trace(sym, axis1=1, axis2=2)[:, None, None] / 3 * np.eye(3)
    shear = rng.uniform(0.0, 6.0, n)[:, None, None]  # deviator over volumetric: both sides of yield
    scale = {"series": 0.003, "quadrature": 0.022}[path]
    F = np.eye(3) + scale * (-np.eye(3) + shear * dev / np.linalg.norm(dev, axis=(1, 2))[:, None, None])
    F = F.astype(np.float32).astype(np.float64)
    lo, hi = STRAIN_PATHS[path]
    norm = np.linalg.norm(F @ F.transpose(0, 2, 1) - np.eye(3), axis=(1, 2))
    assert ((lo < norm) & (norm < hi)).all()  # every state on the path
    got = run_warp(p, F, np.zeros(n))
    F_ref, tau_ref, pl_ref = ref.update(p, F, np.zeros(n), DT)
    yielded = pl_ref > 0
    assert 0.1 < yielded.mean() < 0.9  # both sides sampled
    np.testing.assert_array_equal(got["plastic"] > 0, yielded)
    scale = np.abs(tau_ref).max(axis=(1, 2))
    assert (np.abs(got["tau"] - tau_ref).max(axis=(1, 2)) / scale).max() < 1e-3
    np.testing.assert_allclose(got["F"], F_ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize("model", ["drucker_prager", "mohr_coulomb"])
@pytest.mark.parametrize("cohesion", [0.0, 2.0e3])
@pytest.mark.parametrize("rotated", [False, True])
def test_trial_states_past_the_granular_apex_match_numpy(model, cohesion, rotated):
    """A trial state pulled past the apex (log J at or above the tension strain: sand spreading at
    zero pressure) returns to the isotropic strain there without eigenvectors
    (``hencky_apex_return``): the new F, the stress and the plastic multiplier must be the twin's.
    Cohesionless (the table's sand: the apex at J = 1) and cohesive (the apex above it)."""
    rng = np.random.default_rng(13)
    p = dataclasses.replace(PARAMS[model], cohesion=cohesion)
    apex = 3 * cohesion / np.tan(np.radians(p.friction_angle)) / (3 * p.lam + 2 * p.mu)  # tr eps there
    n = 400
    sym = rng.standard_normal((n, 3, 3))
    sym = 0.5 * (sym + sym.transpose(0, 2, 1))
    dev = sym - np.trace(sym, axis1=1, axis2=2)[:, None, None] / 3 * np.eye(3)
    dev /= np.linalg.norm(dev, axis=(1, 2))[:, None, None]
    volume = rng.uniform(apex / 3 + 1e-4, apex / 3 + 4e-3, n)[:, None, None]  # stretch per axis
    F = np.eye(3) * (1 + volume) + rng.uniform(0.0, 8e-3, n)[:, None, None] * dev
    if rotated:
        q, _ = np.linalg.qr(rng.standard_normal((n, 3, 3)))
        F = q * np.sign(np.linalg.det(q))[:, None, None] @ F
    F = F.astype(np.float32).astype(np.float64)
    assert (np.log(np.linalg.det(F)) >= apex).all()  # past the apex
    assert np.linalg.norm(F @ F.transpose(0, 2, 1) - np.eye(3), axis=(1, 2)).max() < 0.05  # the series' reach
    got = run_warp(p, F, np.zeros(n))
    F_ref, tau_ref, pl_ref = ref.update(p, F, np.zeros(n), DT)
    np.testing.assert_allclose(got["F"], F_ref, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["tau"], tau_ref, rtol=1e-5, atol=1e-6 * p.mu)
    np.testing.assert_allclose(got["plastic"], pl_ref, rtol=1e-4, atol=1e-7)
    # What the apex leaves: F's rotation, scaled to the apex's volume, and an isotropic stress.
    J = np.linalg.det(F_ref)
    np.testing.assert_allclose(J, np.exp(apex), rtol=1e-5)


@wp.kernel
def _log1p_expm1(x: wp.array(dtype=float), out: wp.array2d(dtype=float)):
    i = wp.tid()
    out[i, 0] = log1p(x[i])
    out[i, 1] = expm1(x[i])


def test_log1p_and_expm1_keep_float32_precision_under_the_solver_flags():
    # With reassociation clang folds (1 + x) - 1 to x and log(exp(x)) to x, which undid both
    # tricks: log1p(1e-7) came out 19 % off, log1p(1e-6) 4.6 % (docs/measurements_sim.md section 18).
    x = np.array([1e-7, -3e-7, 1e-6, 2.5e-5, -1e-4, 1e-3, 0.3, -0.5, 2.0], np.float32)
    out = wp.zeros((len(x), 2), dtype=float, device="cpu")
    wp.launch(_log1p_expm1, len(x), [wp.array(x, dtype=float, device="cpu"), out], device="cpu")
    x64 = x.astype(np.float64)
    np.testing.assert_allclose(out.numpy()[:, 0], np.log1p(x64), rtol=3e-7)
    np.testing.assert_allclose(out.numpy()[:, 1], np.expm1(x64), rtol=3e-7)


@wp.kernel
def _is_finite(x: wp.array(dtype=float), out: wp.array(dtype=int)):
    i = wp.tid()
    out[i] = wp.where(is_finite(x[i]), 1, 0)


def test_is_finite_flags_nan_and_infinity_under_the_solver_flags():
    # g2p's divergence guard rests on it; a compiler allowed to assume no NaN or infinity
    # (-ffast-math) would fold it to true.
    big = np.finfo(np.float32).max
    x = np.array([0.0, -1.5, 1e-38, big, -big, np.inf, -np.inf, np.nan], np.float32)
    out = wp.zeros(len(x), dtype=int, device="cpu")
    wp.launch(_is_finite, len(x), [wp.array(x, dtype=float, device="cpu"), out], device="cpu")
    np.testing.assert_array_equal(out.numpy(), np.isfinite(x).astype(int))
