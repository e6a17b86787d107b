"""The 27-node sums of a particle's stencil, as native loops over a node's 8 floats.

A grid node is ``vec8`` (velocity or momentum xyz, mass, velocity change or force xyz, and an
eighth float: ``kernels`` lists what each grid keeps there). Both transfers are one loop over the
stencil's 27 nodes (offset i, j, k = 0..2 from the base node, weight w_n = w[i, 0] w[j, 1]
w[k, 2]) with an inner loop over the node's 8 floats:

    gather_moments   S = sum_n w_n (1, i, j, k) g_n, the sum and its first moments (4 x 8)
    scatter_affine   g_n += w_n (b + i di + j dj + k dk)

On the CPU the loops use clang's 8-float vector type, one AVX register a node: the sub-step runs
1.25x faster than with the same sums in Warp's vec8 arithmetic, and plain C++ loops were slower
than both (docs/measurements_sim.md section 16). There the gather sums each (i, j) column over k
first, then over j and i (the weights factor per axis), and both address the nodes from the
array's pointer and byte stride (section 21). CUDA compiles the portable loops, one thread a
particle, with atomic adds for the scatter.

Nodes are addressed in the flattened node array by one offset per axis: node (i, j, k) of the
stencil is at ``ox[i] + oy[j] + oz[k]`` (``grid_layout.stencil_offsets``), which holds for the
grid's blocked layout as for a plain [nx, ny, nz] one.
``kernels.scatter_particle`` and ``kernels.g2p_kernel`` call these; tests hold both forms to numpy.
"""

from __future__ import annotations

import warp as wp

vec8 = wp.types.vector(length=8, dtype=wp.float32)
# Rows: sum w g, and its first moments sum i w g, sum j w g, sum k w g.
mat48 = wp.types.matrix(shape=(4, 8), dtype=wp.float32)

# Each sum has a portable form (plain loops; CUDA compiles it, one thread a particle) and a CPU
# form on clang's 8-float vector type, one AVX register a node. The snippets pick by
# ``__CUDA_ARCH__``; tests build the portable forms on the CPU too (tests/sim/mpm/test_stencil_sums.py).
GATHER_PORTABLE = """
    wp::mat_t<4, 8, wp::float32> s;
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            for (int k = 0; k < 3; ++k) {
                const wp::vec_t<8, wp::float32> g = *wp::address(grid, ox.c[i] + oy.c[j] + oz.c[k]);
                const float wn = w.data[i][0] * w.data[j][1] * w.data[k][2];
                for (int c = 0; c < 8; ++c) {
                    const float t = wn * g.c[c];
                    s.data[0][c] += t;
                    s.data[1][c] += i * t;
                    s.data[2][c] += j * t;
                    s.data[3][c] += k * t;
                }
            }
        }
    }
    return s;
"""

GATHER_CPU = """
    typedef float f8 __attribute__((vector_size(32)));
    // Separable: the k sums of each (i, j) column first, then j, then i (80 vector products
    // instead of 27 x 5). Nodes are addressed from the array's pointer and byte stride:
    // wp::address per node would redo the index's sign test and multiply 27 times.
    const char* base = reinterpret_cast<const char*>(grid.data);
    const long long stride = grid.strides[0];
    const long long k0 = oz.c[0] * stride, k1 = oz.c[1] * stride, k2 = oz.c[2] * stride;
    const float wk0 = w.data[0][2], wk1 = w.data[1][2], wk2 = w.data[2][2];
    f8 s0 = {}, s1 = {}, s2 = {}, s3 = {};
    for (int i = 0; i < 3; ++i) {
        f8 u = {}, uj = {}, uk = {};
        for (int j = 0; j < 3; ++j) {
            const char* col = base + static_cast<long long>(ox.c[i] + oy.c[j]) * stride;
            f8 g0, g1, g2;
            memcpy(&g0, col + k0, sizeof(g0));
            memcpy(&g1, col + k1, sizeof(g1));
            memcpy(&g2, col + k2, sizeof(g2));
            const f8 t = wk0 * g0 + wk1 * g1 + wk2 * g2;
            const f8 tk = wk1 * g1 + (2.0f * wk2) * g2;
            const float wj = w.data[j][1];
            u += wj * t;
            uj += (static_cast<float>(j) * wj) * t;
            uk += wj * tk;
        }
        const float wi = w.data[i][0];
        s0 += wi * u;
        s1 += (static_cast<float>(i) * wi) * u;
        s2 += wi * uj;
        s3 += wi * uk;
    }
    wp::mat_t<4, 8, wp::float32> s;
    memcpy(s.data[0], &s0, sizeof(s0));
    memcpy(s.data[1], &s1, sizeof(s1));
    memcpy(s.data[2], &s2, sizeof(s2));
    memcpy(s.data[3], &s3, sizeof(s3));
    return s;
"""

SCATTER_PORTABLE = """
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            for (int k = 0; k < 3; ++k) {
                float* g = reinterpret_cast<float*>(wp::address(grid, ox.c[i] + oy.c[j] + oz.c[k]));
                const float wn = w.data[i][0] * w.data[j][1] * w.data[k][2];
                for (int c = 0; c < 8; ++c) {
                    wp::atomic_add(g + c, wn * (b.c[c] + i * di.c[c] + j * dj.c[c] + k * dk.c[c]));
                }
            }
        }
    }
"""

SCATTER_CPU = """
    typedef float f8 __attribute__((vector_size(32)));
    f8 b8, di8, dj8, dk8;
    memcpy(&b8, b.c, sizeof(b8));
    memcpy(&di8, di.c, sizeof(di8));
    memcpy(&dj8, dj.c, sizeof(dj8));
    memcpy(&dk8, dk.c, sizeof(dk8));
    const f8 dk2 = dk8 + dk8;
    char* base = reinterpret_cast<char*>(grid.data);  // as in the gather
    const long long stride = grid.strides[0];
    const long long k0 = oz.c[0] * stride, k1 = oz.c[1] * stride, k2 = oz.c[2] * stride;
    const float wk0 = w.data[0][2], wk1 = w.data[1][2], wk2 = w.data[2][2];
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            char* col = base + static_cast<long long>(ox.c[i] + oy.c[j]) * stride;
            const float wij = w.data[i][0] * w.data[j][1];
            const f8 v0 = b8 + static_cast<float>(i) * di8 + static_cast<float>(j) * dj8;
            f8 n0, n1, n2;
            memcpy(&n0, col + k0, sizeof(n0));
            memcpy(&n1, col + k1, sizeof(n1));
            memcpy(&n2, col + k2, sizeof(n2));
            n0 += (wij * wk0) * v0;
            n1 += (wij * wk1) * (v0 + dk8);
            n2 += (wij * wk2) * (v0 + dk2);
            memcpy(col + k0, &n0, sizeof(n0));
            memcpy(col + k1, &n1, sizeof(n1));
            memcpy(col + k2, &n2, sizeof(n2));
        }
    }
"""


def by_device(portable: str, cpu: str) -> str:
    """One snippet: the portable form on CUDA, the vector form on the CPU."""
    return f"#if defined(__CUDA_ARCH__)\n{portable}\n#else\n{cpu}\n#endif\n"


@wp.func_native(by_device(GATHER_PORTABLE, GATHER_CPU))
def gather_moments(
    grid: wp.array(dtype=vec8),  # [G] the node array, flattened
    ox: wp.vec3i,  # flat offsets of the stencil's three node layers along x (``grid_layout``)
    oy: wp.vec3i,  # along y
    oz: wp.vec3i,  # along z
    w: wp.mat33,  # quadratic weights, row = offset 0..2, column = axis
) -> mat48: ...


@wp.func_native(by_device(SCATTER_PORTABLE, SCATTER_CPU))
def scatter_affine(
    grid: wp.array(dtype=vec8),  # [G] the node array, flattened, added to
    ox: wp.vec3i,  # flat offsets of the stencil's three node layers along x (``grid_layout``)
    oy: wp.vec3i,  # along y
    oz: wp.vec3i,  # along z
    w: wp.mat33,  # quadratic weights, row = offset 0..2, column = axis
    b: vec8,  # the value at the base node (offset 0, 0, 0) before weighting
    di: vec8,  # its change per node along x
    dj: vec8,  # along y
    dk: vec8,  # along z
): ...
