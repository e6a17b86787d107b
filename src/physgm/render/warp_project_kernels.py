"""Warp kernels of the tiled rasteriser, part 1a: EWA projection and its backward (float32).

An (image, Gaussian) pair has index pid = img * N + n and reads Gaussian g = (img // C) * N + n
(``warp_kernels`` describes the whole layout). ``project_pair`` is the projection the renderer
runs inside ``warp_bin_kernels.project_bounds_kernel``; ``project_kernel`` runs it alone and keeps
Warp's generated adjoint, against which the hand-written ``project_vjp_kernel`` is tested. The
math mirrors `projection.py`.
"""

from __future__ import annotations

import warp as wp

from physgm.render.settings import ALPHA_MIN, FOV_CLAMP

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_FOV_CLAMP = wp.constant(FOV_CLAMP)


@wp.func
def quat_to_rotmat(q: wp.vec4) -> wp.mat33:
    """Rotation matrix of a unit quaternion stored (w, x, y, z)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )  # fmt: skip


@wp.func
def pair_gaussian(pid: int, num_gaussians: int, num_cameras: int):
    """Image and Gaussian index of (image, Gaussian) pair ``pid``."""
    img = pid // num_gaussians
    return img, (img // num_cameras) * num_gaussians + (pid - img * num_gaussians)


@wp.func
def to_camera(view: wp.mat44, x: wp.vec3):
    """World-to-camera rotation W of ``view`` and the camera-frame point W x + t."""
    rot_w = wp.mat33(
        view[0, 0], view[0, 1], view[0, 2],
        view[1, 0], view[1, 1], view[1, 2],
        view[2, 0], view[2, 1], view[2, 2],
    )  # fmt: skip
    return rot_w, rot_w * x + wp.vec3(view[0, 3], view[1, 3], view[2, 3])


@wp.func
def clamped_ray(p: wp.vec3, K: wp.mat33, width: int, height: int) -> wp.vec2:
    """(x / z, y / z) clamped to FOV_CLAMP x the half field of view beyond the image border."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x = _FOV_CLAMP * 0.5 * float(width) / fx
    lim_y = _FOV_CLAMP * 0.5 * float(height) / fy
    return wp.vec2(
        wp.min(wp.max(p[0] / p[2], -cx / fx - lim_x), (float(width) - cx) / fx + lim_x),
        wp.min(wp.max(p[1] / p[2], -cy / fy - lim_y), (float(height) - cy) / fy + lim_y),
    )


@wp.func
def cov2d(a0: wp.vec3, a1: wp.vec3, eps2d: float):
    """Entries a0.a0, a0.a1, a1.a1 of the undilated 2D covariance (rows a0, a1 of J W R S) and the
    determinant after adding eps2d to the diagonal (written with |a0 x a1|^2, exact in float32)."""
    cov_a0 = wp.dot(a0, a0)
    cov_b = wp.dot(a0, a1)
    cov_c0 = wp.dot(a1, a1)
    m01 = a0[0] * a1[1] - a0[1] * a1[0]
    m02 = a0[0] * a1[2] - a0[2] * a1[0]
    m12 = a0[1] * a1[2] - a0[2] * a1[1]
    det = m01 * m01 + m02 * m02 + m12 * m12 + eps2d * (cov_a0 + cov_c0) + eps2d * eps2d
    return cov_a0, cov_b, cov_c0, det


@wp.func
def project_pair(
    img: int,
    g: int,
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    viewmats: wp.array(dtype=wp.mat44),
    Ks: wp.array(dtype=wp.mat33),
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
):
    """EWA projection of Gaussian g into image img: (means2d px, conic, depth, diagonal of the 2D
    covariance), all zero when the pair is culled."""
    rot_w, p = to_camera(viewmats[img], means[g])
    z = p[2]
    m2 = wp.vec2(0.0, 0.0)
    con = wp.vec3(0.0, 0.0, 0.0)
    depth = wp.float32(0.0)
    cd = wp.vec2(0.0, 0.0)
    if z >= near_plane and z <= far_plane and opacities[g] >= _ALPHA_MIN:
        K = Ks[img]
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        ray = clamped_ray(p, K, width, height)
        tx = z * ray[0]
        ty = z * ray[1]
        j0 = wp.vec3(fx / z, 0.0, -fx * tx / (z * z))
        j1 = wp.vec3(0.0, fy / z, -fy * ty / (z * z))
        rot_t = wp.transpose(rot_w * quat_to_rotmat(wp.normalize(quats[g])))
        s = scales[g]
        a0 = wp.cw_mul(rot_t * j0, s)  # rows of A = J W R S
        a1 = wp.cw_mul(rot_t * j1, s)
        cov_a0, cov_b, cov_c0, det = cov2d(a0, a1, eps2d)
        if det > 0.0:
            cov_a = cov_a0 + eps2d
            cov_c = cov_c0 + eps2d
            con = wp.vec3(cov_c / det, -cov_b / det, cov_a / det)
            m2 = wp.vec2(fx * p[0] / z + cx, fy * p[1] / z + cy)
            depth = z
            cd = wp.vec2(cov_a, cov_c)
    return m2, con, depth, cd


@wp.kernel
def project_kernel(
    means: wp.array(dtype=wp.vec3),  # [B*N] world (m)
    quats: wp.array(dtype=wp.vec4),  # [B*N] (w, x, y, z), any non-zero norm
    scales: wp.array(dtype=wp.vec3),  # [B*N] linear std (m)
    opacities: wp.array(dtype=float),  # [B*N]
    viewmats: wp.array(dtype=wp.mat44),  # [I] world-to-camera
    Ks: wp.array(dtype=wp.mat33),  # [I]
    num_gaussians: int,
    num_cameras: int,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    means2d: wp.array(dtype=wp.vec2),  # [I*N] px, out
    conics: wp.array(dtype=wp.vec3),  # [I*N] inverse 2D covariance (a, b, c), out
    depths: wp.array(dtype=float),  # [I*N] camera z (m), 0 when culled, out
    cov_diag: wp.array(dtype=wp.vec2),  # [I*N] diagonal of the 2D covariance, 0 when culled, out
):
    """EWA projection of one (image, Gaussian) pair, on its own. The renderer runs it fused with
    the tile bounds (`project_bounds_kernel`); this kernel keeps Warp's generated adjoint, the
    reference `project_vjp_kernel` is tested against."""
    pid = wp.tid()
    img, g = pair_gaussian(pid, num_gaussians, num_cameras)
    m2, con, depth, cd = project_pair(img, g, means, quats, scales, opacities, viewmats, Ks, width, height,
                                      near_plane, far_plane, eps2d)  # fmt: skip
    means2d[pid] = m2
    conics[pid] = con
    depths[pid] = depth
    cov_diag[pid] = cd


@wp.func
def quat_to_rotmat_vjp(q: wp.vec4, v_r: wp.mat33) -> wp.vec4:
    """Gradient of sum(v_r * R(q)) w.r.t. the (unnormalised use of) quaternion q = (w, x, y, z)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return 2.0 * wp.vec4(
        -z * v_r[0, 1] + y * v_r[0, 2] + z * v_r[1, 0] - x * v_r[1, 2] - y * v_r[2, 0] + x * v_r[2, 1],
        y * v_r[0, 1] + z * v_r[0, 2] + y * v_r[1, 0] - 2.0 * x * v_r[1, 1] - w * v_r[1, 2] + z * v_r[2, 0]
        + w * v_r[2, 1] - 2.0 * x * v_r[2, 2],
        -2.0 * y * v_r[0, 0] + x * v_r[0, 1] + w * v_r[0, 2] + x * v_r[1, 0] + z * v_r[1, 2] - w * v_r[2, 0]
        + z * v_r[2, 1] - 2.0 * y * v_r[2, 2],
        -2.0 * z * v_r[0, 0] - w * v_r[0, 1] + x * v_r[0, 2] + w * v_r[1, 0] - 2.0 * z * v_r[1, 1]
        + y * v_r[1, 2] + x * v_r[2, 0] + y * v_r[2, 1],
    )  # fmt: skip


@wp.kernel(enable_backward=False)
def project_vjp_kernel(
    offset: int,  # first pair of this launch (the CPU splits a launch over threads)
    means: wp.array(dtype=wp.vec3),  # [B*N] as in project_kernel
    quats: wp.array(dtype=wp.vec4),  # [B*N]
    scales: wp.array(dtype=wp.vec3),  # [B*N]
    opacities: wp.array(dtype=float),  # [B*N]
    viewmats: wp.array(dtype=wp.mat44),  # [I]
    Ks: wp.array(dtype=wp.mat33),  # [I]
    num_gaussians: int,
    num_cameras: int,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    v_means2d: wp.array(dtype=wp.vec2),  # [I*N] gradient of the loss w.r.t. means2d
    v_conics: wp.array(dtype=wp.vec3),  # [I*N] and w.r.t. conics
    v_means: wp.array(dtype=wp.vec3),  # [B*N] accumulated (summed over cameras), out
    v_quats: wp.array(dtype=wp.vec4),  # [B*N] accumulated, out
    v_scales: wp.array(dtype=wp.vec3),  # [B*N] accumulated, out
):
    """Hand-written vector-Jacobian product of ``project_kernel`` for means, quats and scales.

    Recomputes the pair's forward intermediates and applies the chain rule backwards (conic =
    inverse 2D covariance, covariance = rows a0, a1 of J W R S, J from the clamped ray, mean2d).
    Warp's generated adjoint of ``project_kernel`` is the reference in the tests; this one skips
    the gradients nobody asks for (cameras, opacities) and the replay's bookkeeping.
    """
    pid = wp.tid() + offset
    img, g = pair_gaussian(pid, num_gaussians, num_cameras)
    rot_w, p = to_camera(viewmats[img], means[g])
    z = p[2]
    if z < near_plane or z > far_plane or opacities[g] < _ALPHA_MIN:
        return
    K = Ks[img]
    fx, fy = K[0, 0], K[1, 1]
    rx = p[0] / z
    ry = p[1] / z
    ray = clamped_ray(p, K, width, height)
    cl_x = ray[0]
    cl_y = ray[1]
    tx = z * cl_x
    ty = z * cl_y
    iz = 1.0 / z
    iz2 = iz * iz
    j0 = wp.vec3(fx * iz, 0.0, -fx * tx * iz2)
    j1 = wp.vec3(0.0, fy * iz, -fy * ty * iz2)
    q = quats[g]
    qn = wp.length(q)
    qhat = q / qn
    rot_t = wp.transpose(rot_w * quat_to_rotmat(qhat))
    s = scales[g]
    u0 = rot_t * j0
    u1 = rot_t * j1
    a0 = wp.cw_mul(u0, s)
    a1 = wp.cw_mul(u1, s)
    cov_a0, cov_b, cov_c0, det = cov2d(a0, a1, eps2d)
    if det <= 0.0:
        return
    # conic Q = Sigma^-1: dL/dSigma = -Q G Q with G the symmetric gradient of Q's entries
    inv = wp.mat22(cov_c0 + eps2d, -cov_b, -cov_b, cov_a0 + eps2d) / det
    vc = v_conics[pid]
    v_sigma = -(inv * wp.mat22(vc[0], 0.5 * vc[1], 0.5 * vc[1], vc[2]) * inv)
    v_a0 = 2.0 * v_sigma[0, 0] * a0 + 2.0 * v_sigma[0, 1] * a1
    v_a1 = 2.0 * v_sigma[1, 1] * a1 + 2.0 * v_sigma[0, 1] * a0
    v_s = wp.cw_mul(v_a0, u0) + wp.cw_mul(v_a1, u1)
    v_u0 = wp.cw_mul(v_a0, s)
    v_u1 = wp.cw_mul(v_a1, s)
    v_j0 = wp.transpose(rot_t) * v_u0
    v_j1 = wp.transpose(rot_t) * v_u1
    # rot_t = (W R)^T, so dL/dR = W^T (dL/drot_t)^T
    v_rot = wp.transpose(rot_w) * wp.transpose(wp.outer(v_u0, j0) + wp.outer(v_u1, j1))
    v_qhat = quat_to_rotmat_vjp(qhat, v_rot)
    v_q = (v_qhat - wp.dot(qhat, v_qhat) * qhat) / qn
    # J(tx, ty, z); tx = z clamp(x / z): the gradient reaches x when unclamped, z when clamped
    v_z = -(v_j0[0] * fx + v_j1[1] * fy) * iz2 + 2.0 * (v_j0[2] * fx * tx + v_j1[2] * fy * ty) * iz2 * iz
    v_tx = -v_j0[2] * fx * iz2
    v_ty = -v_j1[2] * fy * iz2
    v_px = wp.float32(0.0)
    v_py = wp.float32(0.0)
    if cl_x == rx:
        v_px = v_tx
    else:
        v_z += v_tx * cl_x
    if cl_y == ry:
        v_py = v_ty
    else:
        v_z += v_ty * cl_y
    vm = v_means2d[pid]
    v_px += vm[0] * fx * iz
    v_py += vm[1] * fy * iz
    v_z -= (vm[0] * fx * p[0] + vm[1] * fy * p[1]) * iz2
    wp.atomic_add(v_means, g, wp.transpose(rot_w) * wp.vec3(v_px, v_py, v_z))
    wp.atomic_add(v_quats, g, v_q)
    wp.atomic_add(v_scales, g, v_s)
