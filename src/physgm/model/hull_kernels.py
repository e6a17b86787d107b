"""Warp kernel of the visual-hull search (pass 2 of ``physgm.model.hull``), one thread per ray.

The torch twin, ``hull._hull_segment_torch``, tests every sample of every ray against every view
at once; this kernel walks a ray's samples from the front until one lies inside all the masks and
then from the back, and leaves a sample at the first view that rejects it. Most points fall
outside the hull, so a ray costs a few projections per sample instead of V, and no [V, R * K]
temporaries are made. The arithmetic is the twin's, in the same order, so both give the same
range up to float rounding at a pixel edge (tests/model/test_hull.py).
"""

from __future__ import annotations

import warp as wp


@wp.func
def _inside_all_masks(
    p: wp.vec3,
    proj: wp.array3d(dtype=wp.float32),  # [V, 3, 4] K [R | t]
    masks: wp.array3d(dtype=wp.uint8),  # [V, H, W] 1 inside
):
    """Whether world point ``p`` falls in front of every camera, in its image and inside its mask."""
    views, height, width = masks.shape[0], masks.shape[1], masks.shape[2]
    for j in range(views):
        x = proj[j, 0, 0] * p[0] + proj[j, 0, 1] * p[1] + proj[j, 0, 2] * p[2] + proj[j, 0, 3]
        y = proj[j, 1, 0] * p[0] + proj[j, 1, 1] * p[1] + proj[j, 1, 2] * p[2] + proj[j, 1, 3]
        z = proj[j, 2, 0] * p[0] + proj[j, 2, 1] * p[1] + proj[j, 2, 2] * p[2] + proj[j, 2, 3]
        if z <= 0.0:
            return False
        zc = wp.max(z, 1.0e-9)
        col = wp.floor(x / zc)
        row = wp.floor(y / zc)
        if col < 0.0 or col >= float(width) or row < 0.0 or row >= float(height):
            return False
        if masks[j, int(row), int(col)] == wp.uint8(0):
            return False
    return True


@wp.kernel
def hull_segment_kernel(
    origin: wp.array(dtype=wp.vec3),  # [R] ray origins (world)
    direction: wp.array(dtype=wp.vec3),  # [R] unit ray directions
    t0: wp.array(dtype=wp.float32),  # [R] start of the ray's part inside every mask frustum
    t1: wp.array(dtype=wp.float32),  # [R] its end (t1 <= t0: the ray misses a frustum)
    fraction: wp.array(dtype=wp.float32),  # [K] sample positions along [t0, t1], 0 ... 1
    proj: wp.array3d(dtype=wp.float32),  # [V, 3, 4]
    masks: wp.array3d(dtype=wp.uint8),  # [V, H, W]
    near: wp.float32,
    far: wp.float32,
    lo: wp.array(dtype=wp.float32),  # [R] out: hull range start, [near, far] when not found
    hi: wp.array(dtype=wp.float32),  # [R] out: hull range end
):
    r = wp.tid()
    a = t0[r]
    b = t1[r]
    lo[r] = near
    hi[r] = far
    if not (b > a):
        return
    o = origin[r]
    d = direction[r]
    samples = fraction.shape[0]
    first = int(-1)  # noqa: UP018 (Warp: a literal is a constant, and the loop below assigns it)
    for k in range(samples):
        t = a + (b - a) * fraction[k]
        if _inside_all_masks(o + t * d, proj, masks):
            first = k
            break
    if first < 0:
        return
    last = int(first)
    for step in range(samples - 1 - first):
        k = samples - 1 - step
        t = a + (b - a) * fraction[k]
        if _inside_all_masks(o + t * d, proj, masks):
            last = k
            break
    spacing = (b - a) / float(samples - 1)
    t_first = a + (b - a) * fraction[first]
    t_last = a + (b - a) * fraction[last]
    lo[r] = wp.min(wp.max(t_first - spacing, near), far)
    hi[r] = wp.min(wp.max(t_last + spacing, near), far)
