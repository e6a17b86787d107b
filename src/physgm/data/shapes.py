"""Procedural shape families for the synthetic assets, as triangle meshes.

Each family draws a random size, aspect ratio and proportions and returns one or more mesh
parts in a local frame whose long axis is +z (so textures such as wood grain follow the
shape). ``make_shape`` then applies a random pose and normalises the object into the
asset frame: centred at the origin, farthest point at radius 0.5, +z up.

A visible cue of stiffness: ``stiffness`` in [0, 1] (the position of the asset's E inside its
material's range) sets the wall thickness of plates and shells, stiffer = thicker.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
import trimesh.creation as tc
import trimesh.remesh

# Radius of the object's bounding sphere in the normalised asset frame.
OBJECT_RADIUS = 0.5
MAX_FACET_EDGE = 0.04  # m in the asset frame; flat-shaded parts are split down to this


@dataclass
class Part:
    """One mesh of an object. ``smooth`` selects interpolated vertex normals over face normals."""

    mesh: trimesh.Trimesh
    smooth: bool


@dataclass
class Shape:
    """A posed, normalised object: asset frame = (R @ local - center) * scale."""

    family: str
    parts: list[Part]  # asset frame (posed and normalised)
    rotation: np.ndarray  # [3, 3] R, local -> asset orientation
    center: np.ndarray  # [3] bounding-box centre of the rotated object, local units
    scale: float  # local units -> asset frame (m)
    thickness: float  # typical material depth below the surface in the asset frame, m

    def texture_coords(self, points: np.ndarray) -> np.ndarray:
        """Asset-frame points [N, 3] -> the local frame at asset scale, where textures live."""
        return (points + self.center * self.scale) @ self.rotation


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(lo + (hi - lo) * rng.random())


def _ellipsoid(rng, stiffness):
    m = tc.icosphere(subdivisions=4)
    m.apply_scale([_u(rng, 0.45, 1.0), _u(rng, 0.45, 1.0), _u(rng, 0.6, 1.3)])
    return [Part(m, True)], 0.3


def _rounded_box_mesh(half: np.ndarray, radius: float) -> trimesh.Trimesh:
    # Minkowski sum of an inner box and a sphere: clamp onto the inner box, push out by ``radius``.
    m = tc.box(extents=2 * half)
    for _ in range(4):
        m = m.subdivide()
    inner = np.maximum(half - radius, 1e-4)
    v = np.asarray(m.vertices)
    core = np.clip(v, -inner, inner)
    d = v - core
    v = core + radius * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return trimesh.Trimesh(v, m.faces, process=False)


def _rounded_box(rng, stiffness):
    half = np.array([_u(rng, 0.3, 0.8), _u(rng, 0.3, 0.8), _u(rng, 0.4, 1.0)])
    m = _rounded_box_mesh(half, _u(rng, 0.04, 0.5) * half.min())
    return [Part(m, True)], 0.3 * half.min()


def _cylinder(rng, stiffness):
    m = tc.cylinder(radius=_u(rng, 0.25, 0.6), height=_u(rng, 0.4, 1.6), sections=48)
    if rng.random() < 0.3:  # elliptic cross-section
        m.apply_scale([1.0, _u(rng, 0.5, 1.0), 1.0])
    return [Part(m, False)], 0.2


def _cone(rng, stiffness):
    m = tc.cylinder(radius=_u(rng, 0.3, 0.6), height=_u(rng, 0.5, 1.4), sections=48)
    top = m.vertices[:, 2] > 0
    v = np.array(m.vertices)
    v[top, :2] *= 0.02 if rng.random() < 0.5 else _u(rng, 0.2, 0.7)  # cone or frustum
    return [Part(trimesh.Trimesh(v, m.faces, process=False), False)], 0.2


def _torus(rng, stiffness):
    major = _u(rng, 0.5, 0.8)
    m = tc.torus(
        major_radius=major, minor_radius=major * _u(rng, 0.2, 0.5), major_sections=48, minor_sections=24
    )
    return [Part(m, True)], 0.1


def _capsule(rng, stiffness):
    m = tc.capsule(height=_u(rng, 0.3, 1.4), radius=_u(rng, 0.2, 0.45), count=[32, 32])
    m.apply_scale([1.0, _u(rng, 0.6, 1.0), 1.0])
    return [Part(m, True)], 0.2


def _superquadric(rng, stiffness):
    m = tc.icosphere(subdivisions=4)
    d = np.asarray(m.vertices)
    e1, e2 = _u(rng, 0.25, 1.8), _u(rng, 0.25, 1.8)  # 1 = ellipsoid, < 1 boxy, > 1 pinched
    abc = np.array([_u(rng, 0.5, 1.0), _u(rng, 0.5, 1.0), _u(rng, 0.6, 1.2)])
    a = np.abs(d / abc) + 1e-12
    f = (a[:, 0] ** (2 / e2) + a[:, 1] ** (2 / e2)) ** (e2 / e1) + a[:, 2] ** (2 / e1)
    v = d * f[:, None] ** (-e1 / 2)  # radial projection onto the inside-outside surface f = 1
    return [Part(trimesh.Trimesh(v, m.faces, process=False), True)], 0.3


def _blob(rng, stiffness):
    m = tc.icosphere(subdivisions=4)
    d = np.asarray(m.vertices)
    r = np.ones(len(d))
    for _ in range(int(rng.integers(3, 7))):
        freq = rng.normal(size=3) * _u(rng, 1.0, 3.0)
        r += _u(rng, 0.04, 0.15) * np.sin(d @ freq + _u(rng, 0, 2 * np.pi))
    v = d * np.clip(r, 0.4, None)[:, None] * np.array([1.0, _u(rng, 0.6, 1.0), _u(rng, 0.7, 1.3)])
    return [Part(trimesh.Trimesh(v, m.faces, process=False), True)], 0.3


def _plate(rng, stiffness):
    thick = 0.03 + 0.12 * stiffness + _u(rng, 0, 0.02)
    if rng.random() < 0.5:
        m = tc.cylinder(radius=1.0, height=thick, sections=64)
        m.apply_scale([1.0, _u(rng, 0.6, 1.0), 1.0])
        part = Part(m, False)
    else:
        half = np.array([1.0, _u(rng, 0.4, 1.0), thick / 2])
        part = Part(_rounded_box_mesh(half, 0.45 * thick), True)
    # Plates stand in the local frame on their long edge so the long axis is +z.
    part.mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return [part], thick / 2


def _shell(rng, stiffness):
    """A bowl, cup or vase wall as a surface of revolution of a closed (r, z) profile."""
    wall = 0.03 + 0.1 * stiffness + _u(rng, 0, 0.02)
    kind = int(rng.integers(3))
    t = np.linspace(0, 1, 16)
    if kind == 0:  # bowl: quarter ellipse
        outer = np.stack([np.sin(t * np.pi / 2), _u(rng, 0.4, 0.9) * (1 - np.cos(t * np.pi / 2))], 1)
    elif kind == 1:  # cup: straight, slightly flared
        outer = np.stack([0.6 + _u(rng, 0, 0.3) * t, 1.4 * t], 1)
        outer = np.vstack([[0.0, 0.0], outer])
    else:  # vase: bulge then neck
        outer = np.stack([0.5 + 0.35 * np.sin(t * np.pi * _u(rng, 0.9, 1.4)), 1.6 * t], 1)
        outer = np.vstack([[0.0, 0.0], outer])
    outer[:, 0] = np.maximum(outer[:, 0], 0.0)
    inner = outer[::-1].copy()
    inner[:, 0] = np.maximum(inner[:, 0] - wall, 0.0)
    inner[:, 1] = np.maximum(inner[:, 1], wall)
    profile = np.vstack([outer, inner])
    profile = profile[np.r_[True, np.any(np.abs(np.diff(profile, axis=0)) > 1e-9, axis=1)]]
    m = tc.revolve(profile, sections=48)
    if m.volume < 0:
        m.invert()
    return [Part(m, True)], wall / 2


_PRIMITIVES_FOR_PARTS = ("ellipsoid", "rounded_box", "cylinder", "capsule", "cone")


def _composite(rng, stiffness):
    """2-4 primitives stacked along z with small sideways offsets, each sunk into the one below."""
    parts: list[Part] = []
    z_top, r_below = 0.0, None
    for i in range(int(rng.integers(2, 5))):
        sub, _ = FAMILIES[_PRIMITIVES_FOR_PARTS[int(rng.integers(len(_PRIMITIVES_FOR_PARTS)))]](
            rng, stiffness
        )
        for p in sub:
            p.mesh.apply_scale(_u(rng, 0.35, 0.8))
            lo, hi = p.mesh.bounds
            r_xy = float(np.min(hi[:2] - lo[:2]) / 2)
            off = np.zeros(3)
            if i:  # offset less than either footprint so the parts stay in contact
                off[:2] = rng.uniform(-0.4, 0.4, size=2) * min(r_xy, r_below)
                off[2] = z_top - lo[2] - 0.15 * (hi[2] - lo[2])
            else:
                off[2] = -lo[2]
            p.mesh.apply_translation(off)
            parts.append(p)
            r_below = r_xy
        z_top = parts[-1].mesh.bounds[1][2]
    return parts, 0.15


FAMILIES: dict[str, Callable[[np.random.Generator, float], tuple[list[Part], float]]] = {
    "ellipsoid": _ellipsoid,
    "rounded_box": _rounded_box,
    "cylinder": _cylinder,
    "cone": _cone,
    "torus": _torus,
    "capsule": _capsule,
    "superquadric": _superquadric,
    "blob": _blob,
    "plate": _plate,
    "shell": _shell,
    "composite": _composite,
}


def random_rotation(rng: np.random.Generator, upright_prob: float = 0.5) -> np.ndarray:
    """A random pose [3, 3]: upright with a random yaw, or uniformly random."""
    if rng.random() < upright_prob:
        a = _u(rng, 0, 2 * np.pi)
        return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return trimesh.transformations.quaternion_matrix(q)[:3, :3]


def make_shape(family: str, rng: np.random.Generator, stiffness: float = 0.5) -> Shape:
    """Build one random object of ``family``, posed and normalised into the asset frame."""
    if family not in FAMILIES:
        raise ValueError(f"unknown shape family {family!r}; choose one of {sorted(FAMILIES)}")
    parts, thickness = FAMILIES[family](rng, stiffness)
    rot = random_rotation(rng)
    verts = np.concatenate([p.mesh.vertices for p in parts]) @ rot.T
    lo, hi = verts.min(0), verts.max(0)
    center = (lo + hi) / 2
    scale = OBJECT_RADIUS / float(np.linalg.norm(verts - center, axis=1).max())
    posed = []
    for p in parts:
        v, f = (np.asarray(p.mesh.vertices) @ rot.T - center) * scale, p.mesh.faces
        if not p.smooth:  # long thin facets (cylinder sides) would gather clumps of samples
            v, f = trimesh.remesh.subdivide_to_size(v, f, max_edge=MAX_FACET_EDGE, max_iter=20)
        posed.append(Part(trimesh.Trimesh(v, f, process=False), p.smooth))
    return Shape(family, posed, rot, center, scale, thickness * scale)


@dataclass
class SurfaceSample:
    """Points sampled uniformly by area on a shape's surface."""

    points: np.ndarray  # [N, 3] asset frame
    normals: np.ndarray  # [N, 3] unit, outward
    area: float  # total surface area, m^2


def sample_surface(parts: list[Part], count: int, rng: np.random.Generator) -> SurfaceSample:
    """Area-uniform samples with smooth (barycentric vertex-normal) or face normals per part."""
    areas = [p.mesh.area_faces for p in parts]
    total = float(sum(a.sum() for a in areas))
    face_part = np.concatenate([np.full(len(a), i) for i, a in enumerate(areas)])
    face_local = np.concatenate([np.arange(len(a)) for a in areas])
    probs = np.concatenate(areas) / total
    # Systematic (stratified) choice of faces: every face gets its expected count rounded up or
    # down, instead of Poisson clumps and gaps that would let the back surface show through.
    cdf = np.cumsum(probs)
    pick = np.minimum(np.searchsorted(cdf, (np.arange(count) + rng.random()) / count), len(probs) - 1)
    r1, r2 = rng.random(count), rng.random(count)
    flip = r1 + r2 > 1  # fold the unit square onto the triangle
    r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
    bary = np.stack([1 - r1 - r2, r1, r2], 1)
    pts = np.empty((count, 3))
    nrm = np.empty((count, 3))
    for i, part in enumerate(parts):
        sel = face_part[pick] == i
        faces = part.mesh.faces[face_local[pick[sel]]]
        tri = part.mesh.vertices[faces]  # [n, 3, 3]
        pts[sel] = np.einsum("nk,nkd->nd", bary[sel], tri)
        if part.smooth:
            nrm[sel] = np.einsum("nk,nkd->nd", bary[sel], part.mesh.vertex_normals[faces])
        else:
            nrm[sel] = part.mesh.face_normals[face_local[pick[sel]]]
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return SurfaceSample(pts, nrm, total)
