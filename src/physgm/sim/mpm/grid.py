"""Box-shaped background grid (origin, cell size, node counts); not necessarily cubic."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GridSpec:
    """Nodes at origin + (i, j, k) dx for 0 <= i < nx, 0 <= j < ny, 0 <= k < nz.

    Args:
        origin: position of node (0, 0, 0), m.
        dx: cell size, m.
        res: node counts (nx, ny, nz); each at least 8 so the boundary margin fits.
    """

    origin: tuple[float, float, float]
    dx: float
    res: tuple[int, int, int]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.dx) and self.dx > 0.0):
            raise ValueError(f"grid cell size dx={self.dx!r} m must be finite and > 0")
        if len(self.res) != 3 or any(int(n) != n or n < 8 for n in self.res):
            raise ValueError(f"grid res={self.res!r} must be three integers >= 8 (nodes per axis)")
        if len(self.origin) != 3 or not all(math.isfinite(o) for o in self.origin):
            raise ValueError(f"grid origin={self.origin!r} must be three finite numbers (m)")
        object.__setattr__(self, "origin", tuple(float(o) for o in self.origin))
        object.__setattr__(self, "res", tuple(int(n) for n in self.res))

    @classmethod
    def fit(
        cls,
        lo: np.ndarray | tuple[float, float, float],  # [3] m
        hi: np.ndarray | tuple[float, float, float],  # [3] m
        dx: float,
        margin_cells: int = 3,
    ) -> GridSpec:
        """Smallest grid whose free interior (``margin_cells`` + 1 cells off each face) holds [lo, hi]."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if (
            lo.shape != (3,)
            or hi.shape != (3,)
            or not np.all(np.isfinite(lo) & np.isfinite(hi))
            or np.any(hi < lo)
        ):
            raise ValueError(f"GridSpec.fit needs finite lo <= hi, got lo={lo}, hi={hi}")
        pad = margin_cells + 1
        origin = lo - pad * dx
        res = np.ceil((hi - lo) / dx - 1e-9).astype(int) + 2 * pad + 1
        return cls(tuple(origin.tolist()), float(dx), tuple(np.maximum(res, 8).tolist()))

    def aligned(self, height: float) -> GridSpec:
        """This grid with its origin lowered by less than a cell so that z = ``height`` (m) is a
        node plane, and one more node along z if it moved, so it still covers this grid.

        The ground's condition needs its held nodes at a fixed depth below the plane
        (``physgm.sim.mpm.boundary``)."""
        oz = self.origin[2]
        shift = (oz - height) / self.dx
        shift = (shift - math.floor(shift)) * self.dx  # in [0, dx)
        if shift < 1e-6 * self.dx or shift > (1.0 - 1e-6) * self.dx:
            return self
        nx, ny, nz = self.res
        return GridSpec((self.origin[0], self.origin[1], oz - shift), self.dx, (nx, ny, nz + 1))

    @property
    def num_nodes(self) -> int:
        return self.res[0] * self.res[1] * self.res[2]

    @property
    def upper(self) -> tuple[float, float, float]:
        """Position of the last node (nx-1, ny-1, nz-1), m."""
        return tuple(o + (n - 1) * self.dx for o, n in zip(self.origin, self.res, strict=True))

    def interior(self, margin_cells: int) -> tuple[np.ndarray, np.ndarray]:
        """[lo, hi] (m) of the region at least ``margin_cells`` cells away from every face."""
        o = np.asarray(self.origin)
        n = np.asarray(self.res)
        return o + margin_cells * self.dx, o + (n - 1 - margin_cells) * self.dx
