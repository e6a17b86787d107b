"""Side walls and periodic axes of a scene, applied to the grid after each grid update.

The ground plane (``boundary.py``) holds z; these are the other walls a laboratory set-up needs,
e.g. a granular column released from a wall at x = 0 in a plane-strain channel:

    Scene(ground=GroundPlane(mode="sticky"),
          walls=(SideWall(axis=0, position=0.0, solid="below", mode="slip"),),
          periodic=(PeriodicAxis(axis=1, lo=0.0, hi=0.02),))

A ``SideWall`` acts like the ground plane does, on the grid nodes on its solid side (at or
beyond the plane): "slip" removes the velocity into the wall and keeps the tangential part (the
matter may leave the wall), "sticky" fixes those nodes. A ``PeriodicAxis`` identifies the
planes ``lo`` and ``hi`` (grid nodes, ``hi - lo`` a whole number of cells): the scatter that
lands on the nodes past one end is folded onto the nodes at the other end before the grid
update (``fold_periodic``), so both images hold the same mass and momentum and compute the same
velocity, and particles that cross an end re-enter at the other (``wrap_periodic``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from physgm.sim.mpm import kernels as K
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.grid_arrays import GridArrays
from physgm.sim.mpm.grid_layout import atomic_add_node, load, store

wp.set_module_options({"enable_backward": False})

_WALL_MODES = {"slip": 0, "sticky": 1}
_SOLID_SIDES = {"below": -1, "above": 1}
GHOST = 3  # nodes past each periodic end that a particle stencil can reach (quadratic: 3)


@dataclass(frozen=True)
class SideWall:
    """The plane x_axis = ``position`` (m); the solid fills the side ``solid`` of it.

    ``solid="below"`` is a wall at the low end of the domain (matter lives at coordinates >=
    position), ``"above"`` one at the high end. ``mode``: "slip" (frictionless, may separate)
    or "sticky" (no motion at the wall).
    """

    axis: int
    position: float
    solid: str = "below"
    mode: str = "slip"

    def __post_init__(self) -> None:
        if self.axis not in (0, 1, 2):
            raise ValueError(f"side wall axis={self.axis!r} must be 0 (x), 1 (y) or 2 (z)")
        if not math.isfinite(self.position):
            raise ValueError(f"side wall position={self.position!r} m must be finite")
        if self.solid not in _SOLID_SIDES:
            raise ValueError(f"side wall solid={self.solid!r} unknown; use 'below' or 'above'")
        if self.mode not in _WALL_MODES:
            raise ValueError(f"side wall mode={self.mode!r} unknown; use one of {', '.join(_WALL_MODES)}")
        object.__setattr__(self, "position", float(self.position))

    def plane(self) -> tuple[tuple[float, float, float], float]:
        """(n, d) with n . p >= d on the free side: the wall as a contact plane of the rigid path."""
        sign = 1.0 if self.solid == "below" else -1.0
        normal = [0.0, 0.0, 0.0]
        normal[self.axis] = sign
        return tuple(normal), sign * self.position

    def holds(self, x: np.ndarray) -> np.ndarray:  # x: [P, 3] m -> [P] bool
        """Which points lie on the free side of the wall."""
        c = x[:, self.axis]
        return c >= self.position if self.solid == "below" else c <= self.position


@dataclass(frozen=True)
class PeriodicAxis:
    """Axis ``axis`` is periodic with period ``hi - lo`` (m); particles live in [lo, hi)."""

    axis: int
    lo: float
    hi: float

    def __post_init__(self) -> None:
        if self.axis not in (0, 1, 2):
            raise ValueError(f"periodic axis={self.axis!r} must be 0 (x), 1 (y) or 2 (z)")
        if not (math.isfinite(self.lo) and math.isfinite(self.hi) and self.hi > self.lo):
            raise ValueError(f"periodic axis needs finite lo < hi, got lo={self.lo}, hi={self.hi}")

    def node_range(self, grid: GridSpec, boundary_cells: int) -> tuple[int, int]:
        """Node indices (i0, i1) of the planes lo and hi; checked to be grid nodes whose ghosts lie
        inside the grid and off its face walls (``boundary_cells``), which would stop them."""
        a, o, dx = self.axis, grid.origin[self.axis], grid.dx
        i0, i1 = (self.lo - o) / dx, (self.hi - o) / dx
        r0, r1 = round(i0), round(i1)
        if abs(i0 - r0) > 1e-4 or abs(i1 - r1) > 1e-4:
            raise ValueError(
                f"periodic axis {a}: lo={self.lo} and hi={self.hi} m must lie on grid nodes "
                f"(origin {o} m, dx {dx} m); choose the grid origin so they do"
            )
        margin = GHOST + boundary_cells
        if r0 < margin or r1 + margin > grid.res[a] or r1 - r0 < 2 * GHOST:
            raise ValueError(
                f"periodic axis {a}: nodes {r0}..{r1} need {margin} free nodes on each side ({GHOST} "
                f"ghosts + {boundary_cells} face-wall cells; res {grid.res[a]}) and a period of at least "
                f"{2 * GHOST} cells; enlarge the grid"
            )
        return r0, r1


@wp.struct
class WallStruct:
    axis: int
    position: float  # m
    side: int  # -1: solid below the plane, +1: solid above
    mode: int  # 0 slip, 1 sticky


def pack_wall(wall: SideWall) -> WallStruct:
    s = WallStruct()
    s.axis = wall.axis
    s.position = wall.position
    s.side = _SOLID_SIDES[wall.solid]
    s.mode = _WALL_MODES[wall.mode]
    return s


@wp.kernel
def apply_walls(
    walls: wp.array(dtype=WallStruct),  # [W]
    num_walls: int,
    lo: wp.vec3i,  # first node of the launched box
    origin: wp.vec3,
    dx: float,
    touched: wp.array3d(dtype=wp.int32),  # [bx, by, bz] blocks the current scatter reached
    stamp: wp.int32,
    impulse: wp.array(dtype=wp.float64),  # [3] running impulse of the walls on the nodes, N s
    grid_v: wp.array4d(dtype=K.vec8),  # [bx, by, bz, 64] in/out (``grid_layout``)
):
    i, j, k = wp.tid()
    i += lo[0]
    j += lo[1]
    k += lo[2]
    # Nodes of blocks no stencil reached hold an older sub-step's values; no particle reads them.
    if not K.block_reached(touched, i // K.BLOCK, j // K.BLOCK, k // K.BLOCK, stamp):
        return
    g = load(grid_v, i, j, k)
    m = g[3]
    if m <= 0.0:
        return
    pos = origin + wp.vec3(float(i), float(j), float(k)) * dx
    v = wp.vec3(g[0], g[1], g[2])
    v_new = v
    for w in range(num_walls):
        wall = walls[w]
        d = float(wall.side) * (pos[wall.axis] - wall.position)  # >= 0: at or inside the wall
        if d >= 0.0:
            if wall.mode == 1:
                v_new = wp.vec3(0.0)
            elif float(wall.side) * v_new[wall.axis] > 0.0:
                v_new[wall.axis] = 0.0
    if wp.length_sq(v_new - v) > 0.0:
        K.set_node_velocity(grid_v, i, j, k, v_new)
        dp = m * (v_new - v)
        for a in range(3):
            wp.atomic_add(impulse, a, wp.float64(dp[a]))


@wp.func
def ghost_and_image(g: int, u: int, w: int, axis: int, i0: int, i1: int):
    """Node of ghost layer ``g`` at (u, w) in the plane across ``axis``, and its periodic image."""
    idx = wp.vec3i(0, 0, 0)
    img = wp.vec3i(0, 0, 0)
    a1 = (axis + 1) % 3
    a2 = (axis + 2) % 3
    idx[a1] = u
    img[a1] = u
    idx[a2] = w
    img[a2] = w
    if g < GHOST:  # below lo: images just below hi
        idx[axis] = i0 - GHOST + g
        img[axis] = i1 - GHOST + g
    else:  # at and past hi: images at and past lo
        idx[axis] = i1 + g - GHOST
        img[axis] = i0 + g - GHOST
    return idx, img


@wp.kernel
def fold_periodic(
    acc0: wp.array4d(dtype=K.vec8),  # [bx, by, bz, 64] first thread's scatter, in/out (``grid_layout``)
    acc1: wp.array4d(dtype=K.vec8),  # [bx, by, bz, 64] second thread's scatter, in/out
    axis: int,
    i0: int,  # node of the plane lo
    i1: int,  # node of the plane hi (same point as i0)
    touched: wp.array3d(dtype=wp.int32),
    stamp: wp.int32,
):
    """Add the scatter on the ghost nodes (GHOST past each end) to their images, one thread per ghost."""
    g, u, w = wp.tid()  # g: ghost layer 0 .. 2 GHOST - 1; (u, w): node in the plane
    idx, img = ghost_and_image(g, u, w, axis, i0, i1)
    s = load(acc0, idx[0], idx[1], idx[2]) + load(acc1, idx[0], idx[1], idx[2])
    if s[3] > 0.0:
        atomic_add_node(acc0, img[0], img[1], img[2], s)
        store(acc0, idx[0], idx[1], idx[2], K.vec8(0.0))
        store(acc1, idx[0], idx[1], idx[2], K.vec8(0.0))
        touched[img[0] // K.BLOCK, img[1] // K.BLOCK, img[2] // K.BLOCK] = stamp


@wp.kernel
def mirror_periodic(
    acc0: wp.array4d(dtype=K.vec8),
    acc1: wp.array4d(dtype=K.vec8),
    axis: int,
    i0: int,
    i1: int,
    touched: wp.array3d(dtype=wp.int32),
    stamp: wp.int32,
):
    """Copy each folded image back onto its ghost, so particles past an end read the same node."""
    g, u, w = wp.tid()
    idx, img = ghost_and_image(g, u, w, axis, i0, i1)
    s = load(acc0, img[0], img[1], img[2]) + load(acc1, img[0], img[1], img[2])
    if s[3] > 0.0:
        store(acc0, idx[0], idx[1], idx[2], s)
        touched[idx[0] // K.BLOCK, idx[1] // K.BLOCK, idx[2] // K.BLOCK] = stamp


@wp.kernel
def wrap_periodic(
    x: wp.array(dtype=wp.vec3),  # [P] m, in/out
    axis: int,
    lo: float,  # m
    hi: float,  # m
):
    p = wp.tid()
    xp = x[p]
    period = hi - lo
    if xp[axis] >= hi:
        xp[axis] = xp[axis] - period
        x[p] = xp
    elif xp[axis] < lo:
        xp[axis] = xp[axis] + period
        x[p] = xp


class SceneWalls:
    """The side walls and periodic axes of one solver's scene; the solver calls the three stages.

    ``impulse`` ([3] float64, N s) is the running impulse of the side walls on the grid, saved and
    restored with the particles when a frame is retried.

    Args:
        walls, periodic: the scene's side walls and periodic axes.
        grid: the grid the solver runs on.
        arrays: the sub-step's grid arrays (``GridArrays``: accumulators, node
            velocities, touched blocks), changed in place.
        boundary_cells: cells of the separating walls inside each grid face (``SolverConfig``).
        device: Warp device.
    """

    def __init__(
        self,
        walls: tuple[SideWall, ...],
        periodic: tuple[PeriodicAxis, ...],
        grid: GridSpec,
        arrays: GridArrays,
        boundary_cells: int,
        device,
    ) -> None:
        self.grid, self.arrays, self.device = grid, arrays, device
        self.walls = tuple(walls)
        self.periodic = tuple(periodic)
        self.ranges = [p.node_range(grid, boundary_cells) for p in self.periodic]
        if len({p.axis for p in self.periodic}) != len(self.periodic):
            raise ValueError("each axis can be periodic only once")
        if any(w.axis == p.axis for w in self.walls for p in self.periodic):
            raise ValueError("an axis cannot have both side walls and a periodic boundary")
        self.impulse = wp.zeros(3, dtype=wp.float64, device=device)
        self._table = wp.array(
            [pack_wall(w) for w in walls] or [WallStruct()], dtype=WallStruct, device=device
        )
        self._origin = wp.vec3(*grid.origin)

    def __bool__(self) -> bool:
        return bool(self.walls or self.periodic)

    def widen_active(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The grid update must cover both images of a periodic axis, wherever the particles are."""
        if not self.periodic:
            return lo, hi
        lo, hi = lo.copy(), hi.copy()
        for p, (i0, i1) in zip(self.periodic, self.ranges, strict=True):
            lo[p.axis] = min(lo[p.axis], i0 - GHOST)
            hi[p.axis] = max(hi[p.axis], i1 + GHOST - 1)
        return lo, hi

    def before_grid_update(self, stamp: int) -> None:
        acc0, acc1 = self.arrays.acc
        for p, (i0, i1) in zip(self.periodic, self.ranges, strict=True):
            res = self.grid.res
            dims = (2 * GHOST, res[(p.axis + 1) % 3], res[(p.axis + 2) % 3])  # the kernels' (u, w) order
            args = [acc0, acc1, p.axis, i0, i1, self.arrays.touched, stamp]
            wp.launch(fold_periodic, dims, args, device=self.device)
            wp.launch(mirror_periodic, dims, args, device=self.device)

    def after_grid_update(self, stamp: int, active_box: tuple[np.ndarray, np.ndarray]) -> None:
        """Apply the side walls to the nodes of ``active_box`` (node index range lo, hi)."""
        if not self.walls:
            return
        g = self.grid
        box_lo, box_hi = active_box
        for wall in self.walls:
            lo, hi = np.array(box_lo), np.array(box_hi)
            c = (wall.position - g.origin[wall.axis]) / g.dx
            if wall.solid == "below":
                hi[wall.axis] = min(hi[wall.axis], math.floor(c + 1e-6))
            else:
                lo[wall.axis] = max(lo[wall.axis], math.ceil(c - 1e-6))
            if np.any(hi < lo):
                continue
            wp.launch(
                apply_walls,
                tuple(int(d) for d in hi - lo + 1),
                [
                    self._table,
                    len(self.walls),
                    wp.vec3i(*lo.tolist()),
                    self._origin,
                    g.dx,
                    self.arrays.touched,
                    stamp,
                    self.impulse,
                    self.arrays.grid_v,
                ],
                device=self.device,
            )

    def after_g2p(self, x: wp.array) -> None:  # x: [P] vec3 particle positions, m, in/out
        for p in self.periodic:
            wp.launch(wrap_periodic, len(x), [x, p.axis, p.lo, p.hi], device=self.device)
