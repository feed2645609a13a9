"""The EM of the unsupervised per-beam intensity calibration (Levinson & Thrun, "Unsupervised Calibration for
Multi-beam Lasers", ISER 2010), as used by the ISHOT paper (Guo et al. 2019, Sec. III-A, eq. 1 and Fig. 7).

Generative model (Levinson & Thrun's "Bayesian generative model of each beam's response"): every map cell ``c``
has a latent reflectivity ``r_c`` on a grid of ``levels`` values; beam ``b`` reading the cell in incidence bin ``i``
returns raw bin ``a`` with probability

    P(a | r, b, i) = (1 - eps) N(a; mu_b(r f_i), sigma(r f_i)) + eps / n_raw

with ``mu_b`` a free non-decreasing response curve per beam (one value per level, no parametric form), ``f_i`` the
Lambertian factor of the incidence bin (1 when incidence is not modelled, as in the original), ``sigma`` a noise
width shared by all beams and ``eps`` an outlier floor. EM over the cells that several beams observe:

* **E-step**: the posterior of every cell's reflectivity given all its observations,
  ``q_c(r) ~ P(r | g_c) prod_o P(a_o | r, b_o, i_o)`` (one sparse matrix product for all cells); the prior is
  estimated per group ``g_c`` = the beam that saw the cell most (upper beams see facades, lower ones kerbs);
* **M-step**: ``mu_b`` = the expected raw value of beam ``b`` at each level over the posterior-weighted cells
  (inliers only), kernel-smoothed over levels, with a weak pseudo-observation at the beam's scaled mean curve
  (levels a beam never sees follow the other beams' shape), made non-decreasing (isotonic regression) with a
  slope of at least half the mean curve's (a plateau would make the table jump);
  ``sigma``, ``eps`` and the priors from the expected counts.

The raw value is regressed on the latent reflectivity (the noise is in the raw value), so noisy beams are not
flattened: the simpler alternation "cell value = mean of its calibrated readings; table = mean cell value per raw
reading" regresses towards the mean at every step and, on the simulator, collapsed through chains of weakly
overlapping beams. EM starts from per-beam gains fitted robustly on all pairs of beams that read the same cells
(`_relative_log_gains`): EM alone moves very slowly along the relative scale of weakly connected groups of beams.

**Gauge.** The reflectivity scale is arbitrary: any increasing relabelling of ``r`` fits the data as well. After
every iteration the grid is relabelled so that the *mean response curve over beams is the identity*
(``mean_b mu_b(r) = r``): reflectivity is reported in the raw units of "the average beam" (``gauge=<beam>``: that
beam's curve is the identity instead). This keeps EM from drifting along the gauge and the grid resolution where
the data are.

**Table.** ``estimate="ml"`` (default): ``mu_b^{-1}(a)``, the maximum-likelihood reflectivity of a single reading
(the inverse response curve, the paper's "most likely true intensity" without a prior); ``"mean"``: the posterior
mean ``E[r | a, b]`` (Levinson & Thrun's expected reflectivity, shrunk towards the prior); ``"map"``: the posterior
mode. Entries with fewer than ``min_count`` observations are filled by linear interpolation between observed
neighbours (identity slope beyond them), and the table is made non-decreasing.

Everything is vectorised over points and cells; Python loops run over EM iterations, cell chunks and beams only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import gaussian_filter1d

from placerec.calibration.observations import Observations
from placerec.calibration.params import CalibrationParams
from placerec.errors import ConfigError, ScanDataError

log = logging.getLogger(__name__)

__all__ = ["LevinsonFit", "fit_levinson"]

_CHUNK = 1 << 16
_MIN_SLOPE = 0.5  # of a response curve, relative to the mean curve (the identity on the regauged grid)
_SHAPE_WEIGHT = 10.0  # pseudo-observations per level pulling a beam's curve towards the scaled mean curve


@dataclass(frozen=True)
class LevinsonFit:
    """Result of `fit_levinson`, all in raw-bin units after the gauge: ``mapping`` (n_beams, n_raw) the table,
    ``counts`` (n_beams, n_raw) observations per entry, ``response`` (n_beams, levels) the forward curves
    ``mu_b`` (expected raw bin) at the reflectivities ``levels`` (gauge units), ``sigma`` (levels,), ``prior``
    (n_beams, levels) the reflectivity prior of the cells each beam dominates, ``outliers`` the outlier fraction,
    ``likelihood`` the log-likelihood per observation after each iteration."""

    mapping: np.ndarray
    counts: np.ndarray
    response: np.ndarray
    levels: np.ndarray
    sigma: np.ndarray
    prior: np.ndarray
    outliers: float
    likelihood: list[float]


def _emission(mu: np.ndarray, sigma: np.ndarray, eps: float, n_raw: int) -> tuple[np.ndarray, np.ndarray]:
    """P(a | r, b, i) (n_beams, n_inc, levels, n_raw) for curves ``mu`` (B, I, R) and widths ``sigma`` (I, R),
    and the inlier share of it."""
    a = np.arange(n_raw, dtype=np.float32)
    z = (a - mu[..., None].astype(np.float32)) / sigma[None, ..., None].astype(np.float32)
    g = np.exp(-0.5 * z * z)
    g /= np.maximum(g.sum(axis=-1, keepdims=True), 1e-30)
    p = (1.0 - eps) * g + eps / n_raw
    return p, (1.0 - eps) * g / p


def _isotonic(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted non-decreasing least-squares fit of ``y`` (pool-adjacent-violators)."""
    vals, wts, lens = [], [], []
    for yi, wi in zip(y.tolist(), w.tolist(), strict=True):
        vals.append(yi)
        wts.append(wi)
        lens.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            wv = wts[-2] + wts[-1]
            vals[-2] = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / wv
            wts[-2] = wv
            lens[-2] += lens[-1]
            del vals[-1], wts[-1], lens[-1]
    return np.repeat(vals, lens)


def _fill_monotone(values: np.ndarray, counts: np.ndarray, min_count: int, top: float) -> np.ndarray:
    """Per beam: isotonic fit over well-observed raw bins, linear fill between them, identity slope outside."""
    n_beams, n_raw = values.shape
    a = np.arange(n_raw, dtype=np.float64)
    out = np.empty_like(values)
    for b in range(n_beams):
        ok = counts[b] >= min_count
        if ok.sum() < 2:
            out[b] = a  # nothing to learn from: leave the beam uncalibrated (identity)
            continue
        x = a[ok]
        y = _isotonic(values[b, ok], counts[b, ok].astype(np.float64))
        v = np.interp(a, x, y)
        v = np.where(a < x[0], y[0] - (x[0] - a), v)
        v = np.where(a > x[-1], y[-1] + (a - x[-1]), v)
        out[b] = np.clip(v, 0.0, top)
    return out


def _relative_log_gains(obs: Observations, min_bin: float) -> np.ndarray:
    """Per-beam log gains ``c_b`` (mean 0) from all pairs of beams reading the same cells: weighted least squares
    on ``mean log(raw)`` differences, readings below ``min_bin`` ignored (offsets dominate there). This starts EM
    with the right relative scale of weakly connected groups of beams, along which EM itself moves very slowly."""
    B = obs.n_beams
    ok = obs.raw_bin >= min_bin
    w = obs.count[ok].astype(np.float64)
    uniq, pair = np.unique(obs.cell[ok] * B + obs.beam[ok], return_inverse=True)
    n = np.bincount(pair, w)
    logx = np.log(obs.raw_bin[ok])
    if obs.inc_factor is not None:
        logx = logx - np.log(obs.inc_factor[obs.inc_index[ok]])
    y = np.bincount(pair, w * logx) / n
    cell, beam = uniq // B, uniq % B
    rows_i, rows_j, diffs, wts = [], [], [], []
    for d in range(1, B):  # entries are sorted by cell: pairs (k, k + d) within one cell
        same = np.flatnonzero(cell[d:] == cell[:-d])
        if same.size == 0:
            break
        rows_i.append(beam[same])
        rows_j.append(beam[same + d])
        diffs.append(y[same] - y[same + d])
        wts.append(n[same] * n[same + d] / (n[same] + n[same + d]))
    c = np.zeros(B)
    if not rows_i:
        return c
    bi, bj, dy, wt = (np.concatenate(v) for v in (rows_i, rows_j, diffs, wts))
    for _ in range(3):  # iteratively reweighted (Cauchy) against mismatched cells
        # normal equations of min sum w (c_i - c_j - dy)^2 + (sum c)^2: a weighted graph Laplacian plus the gauge
        lap = np.bincount(bi * B + bj, -wt, B * B).reshape(B, B)
        lap = lap + lap.T
        lap[np.diag_indices(B)] -= lap.sum(axis=1)
        rhs = np.bincount(bi, wt * dy, B) - np.bincount(bj, wt * dy, B)
        c = np.linalg.lstsq(lap + wt.mean(), rhs, rcond=None)[0]
        r = dy - (c[bi] - c[bj])
        scale = 1.4826 * np.median(np.abs(r)) + 1e-9
        wt = wt / (1.0 + (r / (2.385 * scale)) ** 2)
    seen = np.zeros(B, dtype=bool)
    seen[bi] = seen[bj] = True
    c[~seen] = 0.0
    return c - c[seen].mean()


def _isotonic_rows(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.stack([_isotonic(y[i], w[i]) for i in range(y.shape[0])])


def _at_levels(values: np.ndarray, levels: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """``values`` (..., R) on ``levels`` evaluated at ``levels * f`` for every ``f`` in ``factor``: (..., I, R)."""
    flat = values.reshape(-1, values.shape[-1])
    out = np.stack([np.stack([np.interp(levels * f, levels, v) for f in factor]) for v in flat])
    return out.reshape(*values.shape[:-1], factor.size, levels.size)


def _bin_levels(values: np.ndarray, levels: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """Adjoint of `_at_levels`: sums (B, I, R) values found at ``levels[r] * factor[i]`` onto the grid (B, R),
    splitting each between its two neighbouring levels (linear binning)."""
    B, n_inc, R = values.shape
    pos = np.clip((levels[None, :] * factor[:, None]) / (levels[1] - levels[0]), 0, R - 1)  # (I, R)
    lo = np.minimum(np.floor(pos).astype(np.int64), R - 2)
    frac = pos - lo
    idx = (np.arange(B)[:, None, None] * R + lo[None]).reshape(-1)
    out = np.bincount(idx, (values * (1.0 - frac)[None]).reshape(-1), B * R)
    out += np.bincount(idx + 1, (values * frac[None]).reshape(-1), B * R)
    return out.reshape(B, R)


def fit_levinson(obs: Observations, params: CalibrationParams | None = None) -> LevinsonFit:
    """Run the EM on grouped observations (raw bins ``0..n_raw-1``); returns the gauge-fixed fit."""
    p = params or CalibrationParams()
    if obs.n_cells == 0:
        raise ScanDataError(
            f"no map cell was observed by {p.min_beams} or more beams: registered scans with overlapping views "
            "are needed (more scans, a larger voxel_size, a smaller min_cos_incidence, or check the poses)"
        )
    B, A, R, n_inc = obs.n_beams, obs.binning.n, p.levels, obs.n_inc
    factor = np.ones(1) if obs.inc_factor is None else obs.inc_factor
    top = int(obs.raw_bin.max())
    Af = max(top + 1, 2)  # raw bins that occur: the emission model lives on 0..top
    levels = np.linspace(0.0, 1.25 * top, R)
    col = (obs.beam * n_inc + obs.inc_index) * Af + obs.raw_bin
    N = sp.csr_matrix((obs.count.astype(np.float32), (obs.cell, col)), shape=(obs.n_cells, B * n_inc * Af))
    n_obs = float(obs.count.sum())
    a = np.arange(Af, dtype=np.float64)
    mu = levels[None, :] * np.exp(_relative_log_gains(obs, max(2.0, 0.1 * top)))[:, None]
    sigma = 1.0 + 0.1 * levels
    eps = 0.05
    # one reflectivity prior per group of cells (the beam that observed the cell most often): surfaces seen by the
    # upper beams (facades) and by the lower ones (kerbs, cars) differ, and a shared prior would pull them together
    group = _dominant_beam(obs)
    log_prior = np.full((B, R), -np.log(R))
    smooth = max(p.smoothing * R / 128.0, 0.0)
    history: list[float] = []
    for it in range(p.iterations):
        # emission of beam b in incidence bin i for normal-incidence reflectivity r: the curve at r * factor[i]
        emis, inlier = _emission(_at_levels(mu, levels, factor), _at_levels(sigma, levels, factor), eps, Af)
        W = np.log(emis, dtype=np.float32).transpose(0, 1, 3, 2).reshape(B * n_inc * Af, R)
        expected = np.zeros((B * n_inc * Af, R), dtype=np.float32)
        post_sum = np.zeros((B, R))
        ll = 0.0
        for s in range(0, obs.n_cells, _CHUNK):
            Nc = N[s : s + _CHUNK]
            gc = group[s : s + _CHUNK]
            L = (Nc @ W).astype(np.float64) + log_prior[gc]
            m = L.max(axis=1, keepdims=True)
            q = np.exp(L - m)
            z = q.sum(axis=1, keepdims=True)
            q /= z
            q[q < 1e-12] = 0.0  # no subnormal float32 values: they make the sparse product 10x slower
            ll += float((m + np.log(z)).sum())
            expected += Nc.T @ q.astype(np.float32)
            post_sum += sp.csr_matrix((np.ones(gc.size), (gc, np.arange(gc.size))), shape=(B, gc.size)) @ q
        history.append(ll / n_obs)
        Cin = expected.reshape(B, n_inc, Af, R).transpose(0, 1, 3, 2) * inlier  # (B, I, R, Af) inlier counts
        w_bir = Cin.sum(axis=3)
        num = _bin_levels(Cin @ a, levels, factor)
        w = _bin_levels(w_bir, levels, factor)
        # M-step for the response curves: kernel-smoothed over levels, plus a pseudo-observation at the beam's
        # scaled mean curve (levels a beam has no data for follow the other beams' shape), then non-decreasing
        if smooth > 0:
            num, w_s = gaussian_filter1d(num, smooth, axis=1), gaussian_filter1d(w, smooth, axis=1)
        else:
            w_s = w
        shape = (w_s * mu).sum(axis=0) / np.maximum(w_s.sum(axis=0), 1e-9)
        shape = np.where(w_s.sum(axis=0) > 1e-6, shape, levels)
        scale = (w_s * mu).sum(axis=1) / np.maximum((w_s * shape).sum(axis=1), 1e-9)
        scale = np.where(w_s.sum(axis=1) > 1e-6, scale, 1.0)
        lam = _SHAPE_WEIGHT
        mu = _isotonic_rows((num + lam * scale[:, None] * shape) / (w_s + lam), w_s + lam)
        # no plateaus: a beam responds to every change of reflectivity (slope >= _MIN_SLOPE x the mean curve's)
        mu = _MIN_SLOPE * levels + np.maximum.accumulate(mu - _MIN_SLOPE * levels, axis=1)
        # shared noise width per level: pooled residual variance of the inliers
        mu_i = _at_levels(mu, levels, factor)
        sq = np.einsum("bira,bira->bir", Cin, (a[None, None, None, :] - mu_i[..., None]) ** 2)
        wk = w.sum(axis=0)
        var = _bin_levels(sq, levels, factor).sum(axis=0) / np.maximum(wk, 1e-9)
        ok = wk > 1.0
        if ok.any():
            var = np.interp(levels, levels[ok], var[ok])
            sigma = np.maximum(np.sqrt(gaussian_filter1d(var, 2.0, mode="nearest")), 0.5)
        eps = float(np.clip(1.0 - w_bir.sum() / max(float(expected.sum()), 1e-9), 1e-4, 0.2))
        prior = post_sum / np.maximum(post_sum.sum(axis=1, keepdims=True), 1e-9)
        prior = gaussian_filter1d(prior, 1.0, axis=1, mode="nearest") + 1e-6
        log_prior = np.log(prior / prior.sum(axis=1, keepdims=True))
        # relabel the grid so that the gauge curve is the identity on it: EM cannot drift along the gauge, and
        # the levels keep their resolution where the data are
        mu, sigma, log_prior = _regauge(mu, sigma, log_prior, levels, p.gauge)
        log.debug("EM iteration %d: log-likelihood per observation %.5f", it + 1, history[-1])
        if it > 0 and abs(history[-1] - history[-2]) < p.tolerance:
            break
    log.info(
        "EM: %d iterations, log-likelihood per observation %.4f, outliers %.3f",
        len(history),
        history[-1],
        eps,
    )
    # the table maps a raw value to the reflectivity the beam sees (at the incidence of that reading): the curve's
    # inverse, or the posterior over levels under the emission at the curve itself; reported in gauge units G(r)
    G = _gauge_curve(mu, p.gauge)
    emis, _ = _emission(mu[:, None, :], sigma[None, :], eps, Af)
    post = emis[:, 0] * np.exp(log_prior)[:, :, None]
    post /= np.maximum(post.sum(axis=1, keepdims=True), 1e-300)  # P(r | a, b): (B, R, Af)
    est = np.zeros((B, A))
    if p.estimate == "mean":
        est[:, :Af] = np.einsum("bra,r->ba", post, G)
    elif p.estimate == "map":
        est[:, :Af] = G[np.argmax(post, axis=1)]
    else:
        ramp = 1e-9 * np.arange(R)
        est[:, :Af] = np.stack([np.interp(a, mu[b] + ramp, G) for b in range(B)])
    counts = np.bincount(obs.beam * A + obs.raw_bin, obs.count, B * A).reshape(B, A).astype(np.int64)
    mapping = _fill_monotone(est, counts, p.min_count, float(A - 1))
    return LevinsonFit(mapping, counts, mu, G, sigma, np.exp(log_prior), eps, history)


def _gauge_curve(mu: np.ndarray, gauge: str | int) -> np.ndarray:
    """G(r): the mean response curve over beams (or the reference beam's), made strictly increasing."""
    B, R = mu.shape
    if gauge == "mean":
        G = mu.mean(axis=0)
    else:
        if not 0 <= int(gauge) < B:
            raise ConfigError(f"calibration gauge: beam {gauge} outside 0..{B - 1}")
        G = mu[int(gauge)].copy()
    return np.maximum.accumulate(G) + 1e-6 * np.arange(R)


def _interp_linear(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """`np.interp` with linear extrapolation (the slope over the last tenth of ``xp`` at either end)."""
    k = max(len(xp) // 10, 1)
    lo = (fp[k] - fp[0]) / max(xp[k] - xp[0], 1e-9)
    hi = (fp[-1] - fp[-1 - k]) / max(xp[-1] - xp[-1 - k], 1e-9)
    y = np.interp(x, xp, fp)
    y = np.where(x < xp[0], fp[0] + lo * (x - xp[0]), y)
    return np.where(x > xp[-1], fp[-1] + hi * (x - xp[-1]), y)


def _regauge(
    mu: np.ndarray, sigma: np.ndarray, log_prior: np.ndarray, levels: np.ndarray, gauge: str | int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relabel the latent grid so that G is the identity on it (the grid keeps its resolution where data is)."""
    G = _gauge_curve(mu, gauge)
    src = _interp_linear(levels, G, levels)  # old level whose G equals each new level
    mu = np.stack([_interp_linear(src, levels, m) for m in mu])
    sigma = np.interp(src, levels, sigma)
    prior = np.stack([np.interp(src, levels, np.exp(lp)) for lp in log_prior]) + 1e-9
    return mu, sigma, np.log(prior / prior.sum(axis=1, keepdims=True))


def _dominant_beam(obs: Observations) -> np.ndarray:
    """(n_cells,) the beam with the most observations of each cell."""
    B = obs.n_beams
    uniq, pair = np.unique(obs.cell * B + obs.beam, return_inverse=True)
    n = np.bincount(pair, obs.count)
    cell = uniq // B
    order = np.lexsort((-n, cell))  # per cell, the largest count first
    first = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    out = np.zeros(obs.n_cells, dtype=np.int64)
    out[cell[first]] = uniq[first] % B
    return out
