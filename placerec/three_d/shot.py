"""SHOT and ISHOT descriptors, vectorised over all (keypoint, neighbour) pairs.

Structure (Tombari et al. 2010, PCL features/impl/shot.hpp; ISHOT: Guo et al. 2019, Sec. III-B):

* Support: neighbours within ``support_radius`` R of the keypoint, expressed in its SHOT LRF (`lrf.shot_lrf`).
* 32 volumes = 8 azimuth sectors x 2 radial shells (split at R/2) x 2 elevation halves (split at z = 0).
  The volume index follows PCL: ``vol = 4 * sector + 2 * outer + upper`` with sector s covering azimuths
  [-pi + s pi/4, -pi + (s + 1) pi/4).
* Shape signature: 11 bins per volume over cos(theta) = n_i . z_lrf; bin value ``(1 + cos) * 10 / 2``,
  bin centres at integers 0..10 -> 352 values.
* Intensity signature (ISHOT): 31 bins per volume over the calibrated intensity difference
  ``f = I_P - I_Q`` (keypoint minus neighbour, clipped to [-1, 1]); bin value ``(1 + f) / 2 * 30``, i.e. bin k
  is centred at f = -1 + k/15 with edges at -1 + (k +- 1/2)/15: PCL ColorSHOT's 31 bins over its [0, 1] colour
  distance, stretched to the signed difference. Appended after the shape part: 352 + 992 = 1344 values.
* Interpolation, exactly as PCL: every neighbour adds ``1 - |t|`` per dimension to its own bin and ``|t|``
  to the adjacent bin on its side, for t the signed offset from its bin centre along the cosine (or
  intensity) axis, the radial axis (shell centres R/4, 3R/4), the elevation axis (centres 45 and 135 deg
  from the LRF z axis) and the azimuth axis (circular, sector centres). Offsets towards the outside of the
  support (r < R/4, r > 3R/4, elevation beyond the centres) have no neighbour bin; their share is dropped.
  The own bin thus receives the sum of the four own-weights, each neighbour bin only its offset.
* L2 normalisation of the whole descriptor (PCL ColorSHOT normalises the 1344 vector once:
  ``normalization="joint"``). Since every neighbour casts the same total spatial weight in both signatures,
  the two parts carry equal L1 mass; ``normalization="per_part"`` instead scales each part to norm 1/sqrt(2).

Deviation from PCL (documented): PCL wraps the cosine neighbour bin modulo 10 (bin 9's upper neighbour
becomes bin 0, mixing cos ~ 0.85 with cos = -1; the intensity histogram likewise modulo 30). We use the true
neighbour bin (bin 10) by default; ``pcl_bin_wrap=True`` reproduces PCL. Keypoints without a valid LRF (fewer
than 5 neighbours) get an all-zero row and ``valid=False`` instead of PCL's NaN row.
"""

from __future__ import annotations

import logging
from typing import Any, Literal, cast

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params
from placerec.three_d._neighbors import RadiusPairs, check_points, radius_pairs
from placerec.three_d.lrf import lrf_from_offsets

log = logging.getLogger(__name__)

__all__ = ["SHOTOptions", "SHOTParams", "compute_shot", "N_VOLUMES", "SHAPE_DIM", "ISHOT_DIM"]

N_VOLUMES = 32
SHAPE_BINS = 11
INTENSITY_BINS = 31
SHAPE_DIM = N_VOLUMES * SHAPE_BINS  # 352
ISHOT_DIM = SHAPE_DIM + N_VOLUMES * INTENSITY_BINS  # 1344
_SECTOR = np.pi / 4


class SHOTOptions(Params):
    """SHOT/ISHOT settings besides the support radius (what `placerec.three_d.FeatureParams` exposes)."""

    lrf_radius: float | None = Field(
        None, gt=0, description="m; local reference frame radius (None = support; PCL default)"
    )
    normalization: Literal["joint", "per_part"] = Field(
        "joint", description="L2 over the whole descriptor or per part"
    )
    pcl_bin_wrap: bool = Field(False, description="PCL's wrapped neighbour bins (for comparisons with PCL)")


class SHOTParams(SHOTOptions):
    """Every SHOT/ISHOT setting: the support radius (7 m = ISHOT paper) and `SHOTOptions`."""

    support_radius: float = Field(7.0, gt=0, description="m; descriptor support (ISHOT paper Sec. V-B)")


def _value_bins(value: np.ndarray, n_bins: int, wrap: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Own bin, neighbour bin and neighbour weight for values already scaled to [0, n_bins - 1]."""
    step = np.floor(value + np.float32(0.5))
    frac = value - step
    step = step.astype(np.int32)
    nb = step + ((frac > 0).view(np.int8) << 1) - np.int32(1)
    if wrap:  # PCL: modulo the number of intervals (n_bins - 1)
        nb %= n_bins - 1
    else:
        np.clip(nb, 0, n_bins - 1, out=nb)
    return step, nb, np.abs(frac)


def _spatial_layout(loc: np.ndarray, dist: np.ndarray, R: float):
    """Volume of each pair, its own spatial weight and the (volume, weight) of its radial, elevation and
    azimuth neighbour volumes. ``loc`` (3, M) local coordinates and ``dist`` (> 0) in float32."""
    f32 = np.float32
    x, y, z = loc[0], loc[1] + f32(0.0), loc[2]  # + 0 turns -0.0 into +0.0 for atan2
    upper = z > 0
    outer = dist > f32(R / 2)
    s_up = upper * f32(2) - f32(1)  # +1 upper half, -1 lower half
    s_out = outer * f32(2) - f32(1)  # +1 outer shell, -1 inner shell
    az = np.arctan2(y, x)
    on_axis = (x == 0) & (y == 0)
    sector = np.floor((az + f32(np.pi)) * f32(1 / _SECTOR))
    np.minimum(sector, f32(7), out=sector)
    sector[on_axis] = 0
    # azimuth: circular, sector centres -7pi/8 + s pi/4, unit pi/4; no azimuth vote on the z axis
    t_a = (az + f32(7 * np.pi / 8)) * f32(1 / _SECTOR) - sector
    np.clip(t_a, f32(-0.5), f32(0.5), out=t_a)
    t_a[on_axis] = 0.0
    # small integer dtypes: these arrays are memory-bound
    up8, out8 = upper.view(np.int8), outer.view(np.int8)
    vol = (sector.astype(np.int32) << 2) | (out8 << 1) | up8
    vol_a = (vol + np.int32(4) - ((t_a <= 0).view(np.int8) << 3)) & np.int32(N_VOLUMES - 1)
    w_a = np.abs(t_a)
    # radial: shell centres R/4 (inner) and 3R/4 (outer), unit R/2; only the side between the centres votes
    t_r = (dist - f32(R / 2) - s_out * f32(R / 4)) * f32(2 / R)
    w_r = np.maximum(-s_out * t_r, f32(0))
    # elevation: centres 45 deg (upper) and 135 deg (lower) from the z axis, unit 90 deg
    cos_incl = z / dist
    np.clip(cos_incl, f32(-1), f32(1), out=cos_incl)
    t_e = (np.arccos(cos_incl) - f32(np.pi / 2) + s_up * f32(np.pi / 4)) * f32(2 / np.pi)
    w_e = np.maximum(s_up * t_e, f32(0))
    own = f32(3) - np.abs(t_r) - np.abs(t_e) - w_a - on_axis
    vol_r = vol + np.int32(2) - (out8 << 2)
    vol_e = vol + np.int32(1) - (up8 << 1)
    return vol, own, ((vol_r, w_r), (vol_e, w_e), (vol_a, w_a))


def _signature_votes(out_idx, out_w, base, vol, own, spatial_nbs, value, n_bins, wrap, use):
    """Fill 5 rows of flat histogram indices / weights for one signature: own bin, value-neighbour bin and
    the three spatial-neighbour bins."""
    step, nb_step, w_nb = _value_bins(value, n_bins, wrap)
    n_bins = base.dtype.type(n_bins)
    root = base + vol * n_bins
    np.add(root, step, out=out_idx[0])
    np.multiply(own + (1.0 - w_nb), use, out=out_w[0])
    np.add(root, nb_step, out=out_idx[1])
    np.multiply(w_nb, use, out=out_w[1])
    base_step = base + step
    for r, (nb_vol, nb_w) in enumerate(spatial_nbs, start=2):
        np.add(base_step, nb_vol * n_bins, out=out_idx[r])
        np.multiply(nb_w, use, out=out_w[r])


def compute_shot(
    points: np.ndarray,
    normals: np.ndarray,
    keypoint_indices: np.ndarray,
    params: SHOTParams | None = None,
    intensity: np.ndarray | None = None,
    pairs: RadiusPairs | None = None,
    frames: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """SHOT (352-d) or, with ``intensity``, ISHOT (1344-d) descriptors of the keypoints.

    Returns ``(descriptors (K, D) float32, valid (K,) bool)``. ``intensity``: calibrated, in [0, 1].
    ``pairs``: neighbours of the keypoints (radius >= support radius), searched here if None. ``frames``:
    precomputed (K, 3, 3) LRFs (rows x, y, z; NaN = invalid), computed with `lrf.shot_lrf` if None.
    Neighbours with a non-finite normal are skipped (as PCL does).
    """
    params = params or SHOTParams()
    P = check_points(points)
    n = P.shape[0]
    Nrm = np.asarray(normals, dtype=np.float64)
    if Nrm.shape != (n, 3):
        raise ScanDataError(f"normals must have shape ({n}, 3), got {Nrm.shape}")
    inten = None
    if intensity is not None:
        inten = np.asarray(intensity, dtype=np.float64).reshape(-1)
        if inten.shape[0] != n:
            raise ScanDataError(f"intensity has {inten.shape[0]} values for {n} points")
    kp = np.asarray(keypoint_indices, dtype=np.int64).reshape(-1)
    if kp.size and (kp.min() < 0 or kp.max() >= n):
        raise ScanDataError(f"keypoint indices out of range for {n} points")
    K = kp.size
    D = SHAPE_DIM if inten is None else ISHOT_DIM
    if K == 0:
        return np.zeros((0, D), dtype=np.float32), np.zeros(0, dtype=bool)
    R = float(params.support_radius)
    lrf_r = float(params.lrf_radius or R)
    search_r = max(R, lrf_r)
    if pairs is None or pairs.radius < search_r:
        pairs = radius_pairs(P, P[kp], search_r)
    pr = pairs.within(search_r)
    if pr.n_queries != K:
        raise ScanDataError(f"pairs have {pr.n_queries} queries for {K} keypoints")
    q, j, counts = pr.query, pr.index, pr.counts
    # pair math in float32, structure-of-arrays (3, M), about the cloud centre (~1e-6 m resolution within R);
    # the LRF scatter matrices are accumulated in float64
    PT = np.ascontiguousarray((P - P.mean(axis=0)).T, dtype=np.float32)
    d = PT[:, j] - np.repeat(PT[:, kp], counts, axis=1)
    dist = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    if frames is None:
        frames, valid = lrf_from_offsets(q, pr.splits, d, dist, lrf_r)
    else:
        frames = np.asarray(frames, dtype=np.float64)
        if frames.shape != (K, 3, 3):
            raise ScanDataError(f"frames must have shape ({K}, 3, 3), got {frames.shape}")
        valid = np.isfinite(frames).all(axis=(1, 2))
    good_normal = cast(np.ndarray, np.isfinite(Nrm).all(axis=1))  # (N,): Nrm is 2-D
    NT = np.ascontiguousarray(np.where(good_normal[:, None], Nrm, 0.0).T, dtype=np.float32)
    use = (dist > 0) & (dist <= R) & np.repeat(valid, counts) & good_normal[j]
    F = np.where(valid[:, None, None], frames, np.eye(3)).astype(np.float32)
    Frep = [[np.repeat(F[:, a, b], counts) for b in range(3)] for a in range(3)]
    loc = np.stack([Fa[0] * d[0] + Fa[1] * d[1] + Fa[2] * d[2] for Fa in Frep])
    vol, own, nbs = _spatial_layout(loc, np.maximum(dist, np.float32(1e-30)), R)
    itype: type[np.signedinteger[Any]] = (
        np.int32 if K * D < 2**31 else np.int64
    )  # flat bin indices; int32 halves memory traffic
    base = q.astype(itype) * itype(D)
    Fz = Frep[2]
    cos_z = NT[0, j] * Fz[0] + NT[1, j] * Fz[1] + NT[2, j] * Fz[2]
    np.clip(cos_z, np.float32(-1), np.float32(1), out=cos_z)
    n_sig = 1 if inten is None else 2
    idx = np.empty((5 * n_sig, q.size), dtype=itype)
    w = np.empty((5 * n_sig, q.size), dtype=np.float32)
    shape_value = (cos_z + np.float32(1)) * np.float32((SHAPE_BINS - 1) / 2)
    _signature_votes(idx[:5], w[:5], base, vol, own, nbs, shape_value, SHAPE_BINS, params.pcl_bin_wrap, use)
    if inten is not None:
        i32 = inten.astype(np.float32)
        f = np.clip(np.repeat(i32[kp], counts) - i32[j], np.float32(-1), np.float32(1))
        value = (f + np.float32(1)) * np.float32((INTENSITY_BINS - 1) / 2)
        _signature_votes(
            idx[5:],
            w[5:],
            base + itype(SHAPE_DIM),
            vol,
            own,
            nbs,
            value,
            INTENSITY_BINS,
            params.pcl_bin_wrap,
            use,
        )
    hist: np.ndarray = np.bincount(idx.ravel(), weights=w.ravel(), minlength=K * D).reshape(K, D)
    if inten is not None and params.normalization == "per_part":
        parts = [hist[:, :SHAPE_DIM], hist[:, SHAPE_DIM:]]
        norms = [np.linalg.norm(p, axis=1) for p in parts]
        ok = (norms[0] > 0) & (norms[1] > 0)
        for p, nr in zip(parts, norms, strict=True):
            p /= np.where(ok, nr * np.sqrt(2.0), 1.0)[:, None]
    else:
        nr = np.linalg.norm(hist, axis=1)
        ok = nr > 0
        hist /= np.where(ok, nr, 1.0)[:, None]
    valid &= ok
    hist[~valid] = 0.0
    if not valid.all():
        log.debug("SHOT: %d of %d keypoints without a valid descriptor", int((~valid).sum()), K)
    return hist.astype(np.float32), valid
