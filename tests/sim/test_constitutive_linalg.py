"""The 3x3 eigen solver, rotation-variant SVD and closed-form stretch against numpy."""

from __future__ import annotations

import numpy as np
import warp as wp

from physgm.sim.constitutive import reference as ref
from physgm.sim.constitutive.common import det_minus_one
from physgm.sim.linalg import left_stretch_minus_identity, rv_svd, sym_eig3

wp.set_module_options({"enable_backward": False})


@wp.kernel
def _decompose(
    F: wp.array(dtype=wp.mat33),
    Q: wp.array(dtype=wp.mat33),
    beta: wp.array(dtype=wp.vec3),
    U: wp.array(dtype=wp.mat33),
    sigma: wp.array(dtype=wp.vec3),
    V: wp.array(dtype=wp.mat33),
    stretch: wp.array(dtype=wp.mat33),
):
    n = wp.tid()
    b = F[n] * wp.transpose(F[n])
    q, e = sym_eig3(b)
    Q[n] = q
    beta[n] = e
    u, s, v = rv_svd(F[n])
    U[n] = u
    sigma[n] = s
    V[n] = v
    H = F[n] - wp.identity(n=3, dtype=float)
    stretch[n] = left_stretch_minus_identity(H + wp.transpose(H) + H * wp.transpose(H), det_minus_one(H))


def _cases() -> np.ndarray:
    rng = np.random.default_rng(0)
    general = np.eye(3) + 0.4 * rng.normal(size=(300, 3, 3))
    near_identity = np.eye(3) + 1e-4 * rng.normal(size=(300, 3, 3))
    # Two equal stretches with a distinct third: where the trigonometric solution loses accuracy.
    q, _ = np.linalg.qr(rng.normal(size=(300, 3, 3)))
    repeated = np.einsum("nij,j,nkj->nik", q, [1.2, 1.2, 0.8], q) + 1e-6 * rng.normal(size=(300, 3, 3))
    return np.concatenate([general, near_identity, repeated, np.tile(np.eye(3), (5, 1, 1))]).astype(
        np.float32
    )


def _run(F: np.ndarray):
    n = len(F)
    outs = [
        wp.zeros(n, dtype=t, device="cpu") for t in (wp.mat33, wp.vec3, wp.mat33, wp.vec3, wp.mat33, wp.mat33)
    ]
    wp.launch(_decompose, n, [wp.array(F, dtype=wp.mat33, device="cpu"), *outs], device="cpu")
    return [o.numpy().astype(np.float64) for o in outs]


def test_sym_eig3_reconstructs_and_is_orthonormal():
    F = _cases()
    Q, beta, *_ = _run(F)
    b = np.einsum("nij,nkj->nik", F.astype(np.float64), F)
    np.testing.assert_allclose(np.einsum("nij,nj,nkj->nik", Q, beta, Q), b, atol=2e-5 * (1 + np.abs(b).max()))
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", Q, Q), np.broadcast_to(np.eye(3), Q.shape), atol=2e-6
    )
    np.testing.assert_allclose(np.linalg.det(Q), 1.0, atol=2e-6)
    np.testing.assert_allclose(beta, np.linalg.eigvalsh(b), rtol=2e-5, atol=2e-6)


def test_rotation_variant_svd_matches_numpy():
    F = _cases()
    _, _, U, sigma, V, _ = _run(F)
    F64 = F.astype(np.float64)
    np.testing.assert_allclose(np.einsum("nij,nj,nkj->nik", U, sigma, V), F64, atol=3e-5)
    np.testing.assert_allclose(np.linalg.det(U), 1.0, atol=3e-6)
    np.testing.assert_allclose(np.linalg.det(V), 1.0, atol=3e-6)
    s_ref = np.sort(ref.rv_svd(F64)[1], axis=1)  # numpy: descending with the sign on the smallest
    np.testing.assert_allclose(np.sort(sigma, axis=1), s_ref, atol=2e-5)


def test_closed_form_left_stretch_is_sqrt_of_b():
    F = _cases()
    F = F[np.linalg.det(F) > 0.05]
    stretch = _run(F)[5]
    U, s, Vt = ref.rv_svd(F.astype(np.float64))
    expected = np.einsum("nij,nj,nkj->nik", U, s - 1.0, U)  # V - I
    np.testing.assert_allclose(stretch, expected, atol=3e-5)


def test_left_stretch_keeps_tiny_strains_exact():
    """V - I from b - I: a 1e-6 strain keeps ~6 digits (forming b = I + D first would keep ~1)."""
    rng = np.random.default_rng(1)
    strain = 1e-6 * rng.normal(size=(200, 3, 3))
    strain = 0.5 * (strain + np.swapaxes(strain, 1, 2))
    F = (np.eye(3) + strain).astype(np.float32)  # symmetric: V = F
    H = F.astype(np.float64) - np.eye(3)
    stretch = _run(F)[5]
    np.testing.assert_allclose(stretch, H, atol=1e-12 + 1e-5 * np.abs(H).max())
