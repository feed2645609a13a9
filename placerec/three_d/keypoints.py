"""ISS keypoints with boundary removal (ISS-BR), vectorised over points and neighbour pairs.

Follows PCL's ``ISSKeypoint3D`` (keypoints/impl/iss_3d.hpp):

1. *Boundary points* (``border_radius > 0``): a point with at least ``min_neighbors`` neighbours within
   ``border_radius`` is a boundary point if the largest angular gap between its neighbours, projected on its
   tangent plane (from its normal), exceeds ``angle_threshold`` (pi/2). A point with any boundary point
   within ``border_radius`` (itself included) is a *border* point and cannot be a keypoint.
2. *Saliency*: the scatter matrix of the neighbours within ``salient_radius`` (at least ``min_neighbors``),
   eigenvalues l1 >= l2 >= l3; a point is salient if l2/l1 < gamma_21 and l3/l2 < gamma_32, its saliency
   is l3 (0 otherwise, and for border points).
3. *Non-maximum suppression*: a salient point with at least ``min_neighbors`` neighbours within
   ``non_max_radius`` is a keypoint if no neighbour there has a larger saliency (ties survive, as in PCL;
   values within a relative 1e-9 count as ties, since we evaluate each scatter matrix about its own centre).

``scatter="point"`` is PCL's scatter matrix, sum (p_j - p)(p_j - p)^T about the point itself, not
normalised; ``scatter="centroid"`` is Open3D's (>= 0.13) covariance about the neighbours' mean, divided by
their number, which lets ``border_radius=0`` reproduce ``open3d.geometry.keypoint.compute_iss_keypoints``.
A saliency below 1e-10 * l1 is treated as 0 (exactly planar neighbourhoods give round-off values only).

Defaults: salient radius 2.4 m (paper; 6 x the 0.4 m voxel, PCL's documented 6 x resolution), non-max
radius 1.6 m (PCL's 4 x resolution). Border radius 0.8 m (2 x voxel) rather than PCL's documented 1 x
resolution: around voxel centroids a 0.4 m ball holds only the 4-8 nearest cells, and the angular-gap test
then flags interior points at random (on a jittered 0.4 m grid: ~120-270 false boundaries per 500 interior
points for radii 0.5-0.6 m, none from 0.8 m on, while still finding the rim). On single LiDAR frames most
points far from the sensor are boundary points (ground rings lie further apart than the radius), so ISS-BR
keeps far fewer keypoints there than plain ISS.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params
from placerec.three_d._neighbors import RadiusPairs, check_points, radius_pairs

log = logging.getLogger(__name__)

__all__ = ["ISSParams", "ISSResult", "iss_saliency", "boundary_points", "detect_iss", "sym3_eigvalsh"]

_REL_EPS = 1e-10
_TIE_TOL = 1e-9


class ISSParams(Params):
    """ISS-BR parameters (defaults: ISHOT paper / PCL, see the module docstring). ``border_radius=0`` disables
    boundary removal; ``max_keypoints`` keeps the most salient keypoints after non-maximum suppression (None keeps
    all)."""

    salient_radius: float = Field(2.4, gt=0, description="m; ISHOT paper Sec. V-B (6 x the 0.4 m voxel)")
    non_max_radius: float = Field(1.6, gt=0, description="m; PCL's 4 x resolution")
    gamma_21: float = Field(0.975, gt=0, description="eigenvalue ratio l2/l1 bound; PCL default")
    gamma_32: float = Field(0.975, gt=0, description="eigenvalue ratio l3/l2 bound; PCL default")
    min_neighbors: int = Field(5, ge=1, description="PCL default")
    border_radius: float = Field(0.8, ge=0, description="m; boundary removal (2 x voxel), 0 = off")
    angle_threshold: float = Field(np.pi / 2, gt=0, description="rad; boundary angular gap, PCL default")
    max_keypoints: int | None = Field(None, ge=0, description="most salient kept (None = all)")
    scatter: Literal["point", "centroid"] = Field("point", description="point: PCL; centroid: Open3D")


@dataclass(frozen=True)
class ISSResult:
    """Keypoint indices (int64, most salient first), their saliency (l3) and the per-point masks used."""

    indices: np.ndarray
    saliency: np.ndarray
    boundary: np.ndarray
    border: np.ndarray


def iss_saliency(
    points: np.ndarray, params: ISSParams | None = None, pairs: RadiusPairs | None = None
) -> np.ndarray:
    """Saliency l3 of every point (float64, 0 where the eigenvalue-ratio tests fail); no boundary removal.

    ``pairs``: precomputed neighbours of every point (radius >= ``salient_radius``), else searched here.
    """
    params = params or ISSParams()
    P = check_points(points)
    n = P.shape[0]
    if n == 0:
        return np.zeros(0)
    P = P - P.mean(axis=0)
    if pairs is None:
        pairs = radius_pairs(P, P, params.salient_radius)
    pr = pairs.within(params.salient_radius)
    count = pr.counts.astype(np.float64)
    # per-point sums over the neighbours of p_j and of p_j p_j^T in one sparse product
    a, b = np.triu_indices(3)
    sums = pr.adjacency(n) @ np.concatenate([P, P[:, a] * P[:, b]], axis=1)
    s, spp = sums[:, :3], sums[:, 3:]
    if params.scatter == "point":  # sum (p_j - p)(p_j - p)^T = sum p_j p_j^T - p s^T - s p^T + n p p^T
        S = spp - P[:, a] * s[:, b] - s[:, a] * P[:, b] + count[:, None] * P[:, a] * P[:, b]
    else:  # covariance about the neighbours' mean
        safe = np.maximum(count, 1.0)[:, None]
        m = s / safe
        S = spp / safe - m[:, a] * m[:, b]
    l3, l2, l1 = sym3_eigvalsh(S)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = (l2 / l1 < params.gamma_21) & (l3 / l2 < params.gamma_32)
    ok &= (count >= params.min_neighbors) & (l3 > _REL_EPS * l1)
    return np.where(ok, l3, 0.0)


def sym3_eigvalsh(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues (ascending: smallest, middle, largest) of symmetric 3x3 matrices given by their upper
    triangles ``c`` (N, 6) in the order 00, 01, 02, 11, 12, 22; closed form (trigonometric), float64.

    Error ~1e-16 x the largest eigenvalue when the eigenvalues are apart, up to ~1e-8 x for (nearly)
    repeated ones, which fail ISS's ratio tests anyway; ~8x faster than ``np.linalg.eigvalsh`` on (N, 3, 3).
    """
    scale = np.abs(c).max(axis=1)
    scale[scale == 0] = 1.0
    c = c / scale[:, None]  # entries in [-1, 1]: no under/overflow in p**3
    a00, a01, a02, a11, a12, a22 = (c[:, k] for k in range(6))
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    off = a01 * a01 + a02 * a02 + a12 * a12
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(p > 0, det / (2.0 * p**3), 0.0)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    hi = q + 2.0 * p * np.cos(phi)
    lo = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return lo * scale, (3.0 * q - hi - lo) * scale, hi * scale


def _tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (u, v) spanning the plane orthogonal to each (unit) normal."""
    ax = np.argmin(np.abs(normals), axis=1)
    e = np.zeros_like(normals)
    e[np.arange(normals.shape[0]), ax] = 1.0
    u = np.cross(normals, e)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(normals, u)


def boundary_points(
    points: np.ndarray,
    normals: np.ndarray,
    radius: float,
    angle_threshold: float = np.pi / 2,
    min_neighbors: int = 5,
    pairs: RadiusPairs | None = None,
) -> np.ndarray:
    """Boolean mask of boundary points: largest angular gap of the neighbours within ``radius`` projected
    on the tangent plane > ``angle_threshold`` (points with < ``min_neighbors`` neighbours or a non-finite
    normal are not boundary points).
    """
    P = check_points(points)
    N = np.asarray(normals, dtype=np.float64)
    n = P.shape[0]
    if N.shape != (n, 3):
        raise ScanDataError(f"normals must have shape ({n}, 3), got {N.shape}")
    out = np.zeros(n, dtype=bool)
    if n == 0:
        return out
    pr = (pairs or radius_pairs(P, P, radius)).within(radius)
    norm = np.linalg.norm(N, axis=1)
    good_n = np.isfinite(norm) & (norm > 0)
    testable = good_n & (pr.counts >= min_neighbors)
    unit = np.where(good_n[:, None], N / np.where(good_n, norm, 1.0)[:, None], [0.0, 0.0, 1.0])
    # PCL skips neighbours that coincide with the point; only testable points' pairs are needed
    keep = np.flatnonzero(testable[pr.query] & (pr.dist2 > 0))
    if keep.size == 0:
        return out
    q, j = pr.query.take(keep), pr.index.take(keep)
    u, v = _tangent_basis(unit)
    PT, uT, vT = (np.ascontiguousarray(a.T) for a in (P, u, v))
    d = PT[:, j] - PT[:, q]
    uq, vq = uT[:, q], vT[:, q]
    ang = np.arctan2((d * vq).sum(axis=0), (d * uq).sum(axis=0))
    out[np.unique(q)] = _max_angular_gap(q, ang) > angle_threshold
    return out


def _max_angular_gap(q: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """Largest circular gap between the angles of each group (``q`` non-decreasing), one value per group."""
    new_group = np.r_[True, q[1:] != q[:-1]]
    starts = np.flatnonzero(new_group)
    counts = np.diff(np.r_[starts, q.size])
    kmax = int(counts.max())
    if starts.size * (kmax + 1) <= 4 * q.size + 1024:
        # pad the ragged groups into rows (inf = empty), sort each row; the first empty slot becomes
        # first angle + 2 pi so that the last difference of a row is its wrap-around gap
        group = np.cumsum(new_group) - 1
        rows = np.full((starts.size, kmax + 1), np.inf)
        rows[group, np.arange(q.size) - starts[group]] = ang
        rows.sort(axis=1)
        rows = np.where(np.isinf(rows), rows[:, :1] + 2.0 * np.pi, rows)
        return np.diff(rows, axis=1).max(axis=1)
    # very ragged groups: one stable sort on a composite key instead
    order = np.argsort(q * 8.0 + (ang + np.pi), kind="stable")
    ang = ang[order]
    ends = np.r_[starts[1:], q.size] - 1
    gaps = np.empty_like(ang)
    gaps[1:] = np.diff(ang)
    gaps[starts] = 2.0 * np.pi - (ang[ends] - ang[starts])  # wrap-around gap
    return np.maximum.reduceat(gaps, starts)


def detect_iss(
    points: np.ndarray, normals: np.ndarray | None = None, params: ISSParams | None = None
) -> ISSResult:
    """ISS-BR keypoints of ``points`` (normals needed when ``border_radius > 0``).

    Returns an empty result for clouds with fewer than ``min_neighbors`` points.
    """
    params = params or ISSParams()
    P = check_points(points)
    n = P.shape[0]
    if n < params.min_neighbors:
        z = np.zeros(n, dtype=bool)
        return ISSResult(np.zeros(0, dtype=np.int64), np.zeros(0), z, z.copy())
    use_br = params.border_radius > 0
    if use_br and normals is None:
        raise ScanDataError("ISS with boundary removal needs normals (or set border_radius=0)")
    P = P - P.mean(axis=0)
    r_max = max(params.salient_radius, params.non_max_radius, params.border_radius)
    pairs = radius_pairs(P, P, r_max)
    saliency = iss_saliency(P, params, pairs)
    boundary = np.zeros(n, dtype=bool)
    border = np.zeros(n, dtype=bool)
    if use_br:
        assert normals is not None  # checked above
        br_pairs = pairs.within(params.border_radius)
        boundary = boundary_points(
            P, normals, params.border_radius, params.angle_threshold, params.min_neighbors, br_pairs
        )
        border = np.bincount(br_pairs.query, weights=boundary[br_pairs.index], minlength=n) > 0
        saliency = np.where(border, 0.0, saliency)
    nm = pairs.within(params.non_max_radius)
    neigh_max = np.full(n, -np.inf)
    nonempty = nm.counts > 0
    neigh_max[nonempty] = np.maximum.reduceat(saliency[nm.index], nm.splits[:-1][nonempty])
    # ties survive (PCL: "l3 < l3_j" suppresses); identical neighbourhoods evaluated about different centres
    # differ by round-off only, hence the relative tolerance
    is_kp = (saliency > 0) & (nm.counts >= params.min_neighbors) & (saliency >= neigh_max * (1 - _TIE_TOL))
    idx = np.flatnonzero(is_kp)
    idx = idx[np.argsort(-saliency[idx], kind="stable")]
    if params.max_keypoints is not None:
        idx = idx[: params.max_keypoints]
    log.debug(
        "ISS: %d points, %d salient, %d boundary, %d border, %d keypoints",
        n,
        int((saliency > 0).sum()),
        int(boundary.sum()),
        int(border.sum()),
        idx.size,
    )
    return ISSResult(idx.astype(np.int64), saliency[idx], boundary, border)
