"""3D Gaussians: the one container every part of physgm passes around, and 3DGS PLY files.

Conventions: means in metres, unit quaternions (w, x, y, z), *linear* scales (standard deviations
in metres, not logs), opacities in [0, 1], colours RGB in [0, 1] (spherical harmonics degree 0).
The PLY layout is the one of the original 3D Gaussian Splatting code, so common viewers open our
files and PLYs written by other tools load here: logits for opacity, logs for scale, SH DC
coefficients for colour.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

# Zeroth spherical-harmonic basis constant: colour = SH_C0 * f_dc + 0.5.
SH_C0 = 0.28209479177387814


@dataclass
class Gaussians:
    """A set of N 3D Gaussians.

    Attributes:
        means: [N, 3] centres, m.
        quats: [N, 4] unit quaternions (w, x, y, z).
        scales: [N, 3] standard deviations along the local axes, m.
        opacities: [N] in [0, 1].
        colors: [N, 3] RGB in [0, 1] (SH degree 0).
        sh_rest: [N, K, 3] higher-order SH coefficients kept from a PLY, or None.
    """

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4]
    scales: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    colors: Tensor  # [N, 3]
    sh_rest: Tensor | None = None  # [N, K, 3]

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        widths = {"means": 3, "quats": 4, "scales": 3, "opacities": None, "colors": 3}
        for name, width in widths.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor):
                raise TypeError(f"Gaussians.{name} must be a torch.Tensor, got {type(value).__name__}")
            shape, text = ((n,), "[N]") if width is None else ((n, width), f"[N, {width}]")
            if tuple(value.shape) != shape:
                raise ValueError(
                    f"Gaussians.{name} must have shape {text} with N = {n}, got {tuple(value.shape)}"
                )
        if self.sh_rest is not None and (
            self.sh_rest.ndim != 3 or self.sh_rest.shape[0] != n or self.sh_rest.shape[2] != 3
        ):
            raise ValueError(
                f"Gaussians.sh_rest must have shape [N, K, 3] with N = {n}, got {tuple(self.sh_rest.shape)}"
            )

    def __len__(self) -> int:
        return self.means.shape[0]

    def _map(self, fn) -> Gaussians:
        return Gaussians(
            **{
                f.name: None if getattr(self, f.name) is None else fn(getattr(self, f.name))
                for f in fields(self)
            }
        )

    def __getitem__(self, index) -> Gaussians:
        """Select Gaussians by integer index tensor, boolean mask [N] or slice."""
        return self._map(lambda t: t[index])

    def to(self, device: torch.device | str) -> Gaussians:
        return self._map(lambda t: t.to(device))

    def detach(self) -> Gaussians:
        return self._map(lambda t: t.detach())

    @property
    def device(self) -> torch.device:
        return self.means.device

    @staticmethod
    def cat(parts: list[Gaussians]) -> Gaussians:
        """Concatenate along N. SH beyond degree 0 is kept only if every part has the same K."""
        if not parts:
            raise ValueError("Gaussians.cat needs at least one Gaussians object, got an empty list")
        rest = [p.sh_rest for p in parts]
        keep_rest = all(r is not None for r in rest) and len({r.shape[1] for r in rest}) == 1
        if not keep_rest and any(r is not None for r in rest):
            warnings.warn(
                "Gaussians.cat: parts have different SH degrees; higher-order SH dropped", stacklevel=2
            )
        return Gaussians(
            means=torch.cat([p.means for p in parts]),
            quats=torch.cat([p.quats for p in parts]),
            scales=torch.cat([p.scales for p in parts]),
            opacities=torch.cat([p.opacities for p in parts]),
            colors=torch.cat([p.colors for p in parts]),
            sh_rest=torch.cat(rest) if keep_rest else None,
        )

    def covariances(self) -> Tensor:
        """World-space covariances R diag(s^2) R^T, [N, 3, 3] in m^2."""
        rot = quat_to_rotmat(self.quats)
        rs = rot * self.scales[:, None, :]
        return rs @ rs.transpose(-1, -2)

    def prune(self, min_opacity: float) -> Gaussians:
        """Drop Gaussians whose opacity is below ``min_opacity``."""
        return self[self.opacities >= min_opacity]


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions (w, x, y, z), normalised first.

    Args:
        quats: [..., 4].
    Returns:
        [..., 3, 3].
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    entries = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(entries, dim=-1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(rot: Tensor) -> Tensor:
    """Unit quaternions (w, x, y, z) with w >= 0 from rotation matrices.

    Args:
        rot: [..., 3, 3] proper rotations.
    Returns:
        [..., 4].
    """
    m = rot
    # Shepperd's method: pick the largest of (w, x, y, z) to divide by, stable for every rotation.
    t = torch.stack(
        [
            1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2],
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        dim=-1,
    )
    k = t.argmax(dim=-1, keepdim=True)
    s = torch.sqrt(t.gather(-1, k).clamp_min(1e-12)).squeeze(-1) * 2  # 4 * largest component
    cands = torch.stack(
        [
            torch.stack(
                [
                    s / 4,
                    (m[..., 2, 1] - m[..., 1, 2]) / s,
                    (m[..., 0, 2] - m[..., 2, 0]) / s,
                    (m[..., 1, 0] - m[..., 0, 1]) / s,
                ],
                -1,
            ),
            torch.stack(
                [
                    (m[..., 2, 1] - m[..., 1, 2]) / s,
                    s / 4,
                    (m[..., 0, 1] + m[..., 1, 0]) / s,
                    (m[..., 0, 2] + m[..., 2, 0]) / s,
                ],
                -1,
            ),
            torch.stack(
                [
                    (m[..., 0, 2] - m[..., 2, 0]) / s,
                    (m[..., 0, 1] + m[..., 1, 0]) / s,
                    s / 4,
                    (m[..., 1, 2] + m[..., 2, 1]) / s,
                ],
                -1,
            ),
            torch.stack(
                [
                    (m[..., 1, 0] - m[..., 0, 1]) / s,
                    (m[..., 0, 2] + m[..., 2, 0]) / s,
                    (m[..., 1, 2] + m[..., 2, 1]) / s,
                    s / 4,
                ],
                -1,
            ),
        ],
        dim=-2,
    )
    q = cands.gather(-2, k[..., None].expand(*k.shape[:-1], 1, 4)).squeeze(-2)
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    return q / q.norm(dim=-1, keepdim=True)


# ----------------------------------------------------------------------------------------------
# PLY I/O in the standard 3D Gaussian Splatting layout.

_PLY_BASE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
_PLY_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-7, 1 - 1e-7)
    return np.log(p) - np.log1p(-p)


def write_ply(gaussians: Gaussians, path: str | os.PathLike) -> None:
    """Write Gaussians as a binary little-endian 3DGS PLY, atomically (temp file then rename)."""
    from plyfile import PlyData, PlyElement

    g = gaussians.detach().to("cpu")
    n = len(g)
    rest = g.sh_rest
    # 3DGS stores f_rest channel-major: all coefficients of R, then G, then B.
    rest_flat = None if rest is None else rest.permute(0, 2, 1).reshape(n, -1).double().numpy()
    names = (
        _PLY_BASE + [f"f_rest_{i}" for i in range(0 if rest_flat is None else rest_flat.shape[1])] + _PLY_TAIL
    )
    data = np.zeros(n, dtype=[(name, "<f4") for name in names])
    means = g.means.double().numpy()
    data["x"], data["y"], data["z"] = means.T
    dc = (g.colors.double().numpy() - 0.5) / SH_C0
    for i in range(3):
        data[f"f_dc_{i}"] = dc[:, i]
    if rest_flat is not None:
        for i in range(rest_flat.shape[1]):
            data[f"f_rest_{i}"] = rest_flat[:, i]
    data["opacity"] = _logit(g.opacities.double().numpy())
    log_scales = np.log(np.maximum(g.scales.double().numpy(), 1e-30))
    quats = torch.nn.functional.normalize(g.quats.double(), dim=-1).numpy()
    for i in range(3):
        data[f"scale_{i}"] = log_scales[:, i]
    for i in range(4):
        data[f"rot_{i}"] = quats[:, i]

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        PlyData([PlyElement.describe(data, "vertex")], text=False).write(str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_ply(path: str | os.PathLike, keep_sh: bool = True) -> Gaussians:
    """Read a 3DGS PLY (ours or another tool's).

    Args:
        path: file written in the 3DGS layout (binary or ASCII).
        keep_sh: keep degree > 0 SH coefficients in ``sh_rest``; if False they are dropped with a warning,
            since physgm renders SH degree 0 only.
    """
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PLY file at {path}")
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except Exception as err:  # plyfile raises several types for malformed files
        raise ValueError(f"{path} is not a readable PLY file ({err})") from err
    props = {p.name for p in vertex.properties}
    missing = [
        name for name in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + _PLY_TAIL if name not in props
    ]
    if missing:
        raise ValueError(
            f"{path} is not a 3D Gaussian Splatting PLY: missing properties {missing}. "
            "Expected x y z f_dc_0..2 opacity scale_0..2 rot_0..3 (the layout of the original 3DGS code)."
        )

    def col(name: str) -> np.ndarray:
        return np.asarray(vertex[name], dtype=np.float64)

    n = len(vertex["x"])
    means = np.stack([col("x"), col("y"), col("z")], -1)
    colors = np.stack([col(f"f_dc_{i}") for i in range(3)], -1) * SH_C0 + 0.5
    opac = 1.0 / (1.0 + np.exp(-col("opacity")))
    scales = np.exp(np.stack([col(f"scale_{i}") for i in range(3)], -1))
    quats = np.stack([col(f"rot_{i}") for i in range(4)], -1)
    norms = np.linalg.norm(quats, axis=-1, keepdims=True)
    quats = np.where(norms > 0, quats / np.maximum(norms, 1e-30), np.array([1.0, 0, 0, 0]))
    rest_names = sorted((p for p in props if p.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
    sh_rest = None
    if rest_names:
        if keep_sh and len(rest_names) % 3 == 0:
            rest = np.stack([col(name) for name in rest_names], -1).reshape(n, 3, -1).transpose(0, 2, 1)
            sh_rest = torch.from_numpy(np.ascontiguousarray(rest)).float()
        else:
            degree = int(math.isqrt(len(rest_names) // 3 + 1)) - 1
            warnings.warn(
                f"{path}: dropping SH degree {degree} coefficients; physgm renders SH degree 0", stacklevel=2
            )
    values = {"means": means, "colors": colors, "scales": scales, "quats": quats}
    for name, value in values.items():
        if not np.isfinite(value).all():
            raise ValueError(f"{path}: non-finite values in {name}; the file is corrupt")
    return Gaussians(
        means=torch.from_numpy(means).float(),
        quats=torch.from_numpy(quats).float(),
        scales=torch.from_numpy(scales).float(),
        opacities=torch.from_numpy(opac).float(),
        colors=torch.from_numpy(colors).float(),
        sh_rest=sh_rest,
    )
