"""The posterior over places of the ISHOT paper's probabilistic voting (Sec. IV-C/E, eq. 6, Fig. 4).

For every vote ``{rho_v, tau_v}`` the paper looks up a precomputed probability vector over all places,
``P(rho_i | v)`` = the vote model (eq. 7, `placerec.three_d.vote_model`) at the distance between place ``i`` and the
voted place (standing in for the unknown true place), normalised to sum to 1 over the places, and multiplies it into
the running posterior (eq. 6): ``P(kappa = rho_i) = eta * prod_m P(rho_i | v_m)``.

`PosteriorTable` holds those vectors for every (voted place, tau range) and `Posterior` applies them, in log space.
Dividing the unnormalised vector ``lambda hn(d) + (1 - lambda) / d_max`` by its uniform floor gives
``1 + lambda hn(d) d_max / (1 - lambda)``: the normaliser of each vector and its floor are the same for every place
of the vector, so they cancel in ``eta`` and only the places where the half-normal term is not negligible change
the posterior. ``mode="sparse"`` (default) stores just those: places where ``lambda hn(d) > truncation * (1 -
lambda) / d_max``, i.e. within a few sigma of the voted place; every other entry equals the floor up to a relative
``truncation`` (1e-3), so the sparse posterior matches the full one to that tolerance. Memory grows with the
number of places times the places within reach of a vote, not with its square: ``mode="full"`` stores the dense
(places, ranges, places) table of the paper, `nbytes` reports either (docs/localization.md has the measurements).

Keypoint density (Sec. IV-E, "additional normalization"): a place described by many keypoints collects more
chance votes than a sparse one. With ``weights`` each vote's log-vector is scaled by ``mean count / count of the
voted place``, so that the expected chance votes of every place move the posterior equally.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt

from placerec.errors import ScanDataError
from placerec.three_d.vote_model import VoteModel

__all__ = ["PosteriorTable", "Posterior", "density_weights"]


def density_weights(counts: npt.ArrayLike) -> np.ndarray:
    """``mean(counts) / counts`` per place (keypoint-density correction); 0 for a place without keypoints (it
    gets no votes)."""
    c = np.asarray(counts, np.float64)
    mean = float(c[c > 0].mean()) if (c > 0).any() else 1.0
    with np.errstate(divide="ignore"):
        return np.where(c > 0, mean / np.maximum(c, 1e-12), 0.0)


class PosteriorTable:
    """The precomputed log-vectors of every (voted place, tau range), relative to their uniform floor."""

    def __init__(
        self,
        model: VoteModel,
        place_xyz: np.ndarray,
        mode: Literal["sparse", "full"] = "sparse",
        truncation: float = 1e-3,
    ) -> None:
        xyz = np.asarray(place_xyz, np.float64).reshape(-1, 3)
        if xyz.shape[0] == 0 or not np.isfinite(xyz).all():
            raise ScanDataError(
                f"posterior: place positions must be finite (P, 3) with P > 0, got {xyz.shape}"
            )
        if mode not in ("sparse", "full"):
            raise ScanDataError(f"posterior: mode must be 'sparse' or 'full', got {mode!r}")
        self.model, self.mode, self.truncation = model, mode, float(truncation)
        self.n_places, self.n_ranges = int(xyz.shape[0]), model.n_ranges
        lam, sig = model.lam, model.sigma
        # log(1 + lambda hn(d) d_max / (1 - lambda)) = log(1 + a_r exp(-d^2 / 2 sigma_r^2))
        self._a = lam * np.sqrt(2.0) / (sig * np.sqrt(np.pi)) * model.d_max / (1.0 - lam)
        if mode == "full":
            d = np.linalg.norm(xyz[:, None, :] - xyz[None, :, :], axis=2)
            self.full = np.log1p(
                self._a[None, :, None] * np.exp(-(d[:, None, :] ** 2) / (2.0 * sig[None, :, None] ** 2))
            ).astype(np.float32)
            return
        from scipy.spatial import cKDTree

        # the half-normal term is below truncation * floor beyond this radius (no radius where a_r <= truncation)
        ratio = np.maximum(self._a / self.truncation, 1.0)
        reach = sig * np.sqrt(2.0 * np.log(ratio))
        tree = cKDTree(xyz)
        idx_parts, val_parts, counts = [], [], np.zeros(self.n_places * self.n_ranges, np.int64)
        for r in range(self.n_ranges):
            if reach[r] <= 0:
                continue
            nbrs = tree.query_ball_point(xyz, r=float(reach[r]))
            for v, nb in enumerate(nbrs):
                nb = np.asarray(nb, np.int64)
                d2 = np.sum((xyz[nb] - xyz[v]) ** 2, axis=1)
                idx_parts.append((v * self.n_ranges + r, nb))
                val_parts.append(np.log1p(self._a[r] * np.exp(-d2 / (2.0 * sig[r] ** 2))).astype(np.float32))
                counts[v * self.n_ranges + r] = nb.size
        order = sorted(range(len(idx_parts)), key=lambda k: idx_parts[k][0])
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.indices = (
            np.concatenate([idx_parts[k][1] for k in order]).astype(np.int32)
            if order
            else np.zeros(0, np.int32)
        )
        self.values = (
            np.concatenate([val_parts[k] for k in order]).astype(np.float32)
            if order
            else np.zeros(0, np.float32)
        )

    @property
    def nbytes(self) -> int:
        """Bytes held by the table."""
        if self.mode == "full":
            return int(self.full.nbytes)
        return int(self.offsets.nbytes + self.indices.nbytes + self.values.nbytes)

    def vector(self, voted: int, tau_range: int) -> np.ndarray:
        """``P(rho_i | v)`` for every place ``i``: the normalised probability vector of one vote."""
        lv = np.zeros(self.n_places)
        if self.mode == "full":
            lv[:] = self.full[voted, tau_range]
        else:
            k = voted * self.n_ranges + tau_range
            a, b = self.offsets[k], self.offsets[k + 1]
            lv[self.indices[a:b]] = self.values[a:b]
        p = np.exp(lv)
        return p / p.sum()

    def add(
        self, log_post: np.ndarray, voted: np.ndarray, tau_range: np.ndarray, weights: np.ndarray
    ) -> None:
        """Eq. 6 for a batch of votes: ``log_post += w * log(P(rho | v) / floor)`` for every vote, in place."""
        voted = np.asarray(voted, np.int64)
        rr = np.asarray(tau_range, np.int64)
        w = np.asarray(weights, np.float64)
        if voted.size == 0:
            return
        if self.mode == "full":
            log_post += np.einsum("k,kp->p", w, self.full[voted, rr].astype(np.float64))
            return
        k = voted * self.n_ranges + rr
        starts, ends = self.offsets[k], self.offsets[k + 1]
        lens = ends - starts
        if lens.sum() == 0:
            return
        # gather every vote's slice of the CSR arrays at once
        pos = np.repeat(starts - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens) + np.arange(lens.sum())
        np.add.at(log_post, self.indices[pos], np.repeat(w, lens) * self.values[pos])


class Posterior:
    """The running posterior over places (eq. 6) of one query."""

    def __init__(self, table: PosteriorTable, weights: np.ndarray | None = None) -> None:
        self.table = table
        self.log = np.zeros(table.n_places)
        self.weights = np.ones(table.n_places) if weights is None else np.asarray(weights, np.float64)
        self.n_votes = 0

    def update(self, voted: np.ndarray, tau_range: np.ndarray) -> None:
        """Multiply the vectors of these votes into the posterior."""
        voted = np.asarray(voted, np.int64)
        self.table.add(self.log, voted, tau_range, self.weights[voted])
        self.n_votes += int(voted.size)

    def scale(self, mask: np.ndarray, factor: float) -> None:
        """Multiply the posterior of the places in ``mask`` by ``factor`` (evidence against them, e.g. a rejected
        verification); the others gain by the renormalisation."""
        if factor <= 0:
            raise ScanDataError(f"posterior: a scale factor must be > 0, got {factor}")
        self.log[np.asarray(mask, bool)] += np.log(factor)

    @property
    def probabilities(self) -> np.ndarray:
        """The normalised posterior (sums to 1; uniform before any vote)."""
        p = np.exp(self.log - self.log.max())
        return p / p.sum()
