"""The vote model of the ISHOT paper (Sec. IV-D, eq. 7, Fig. 5): how far a descriptor's vote lands from the truth.

A vote ``{rho_v, tau_v}`` (eq. 5) names the place of a query descriptor's nearest database neighbour and the ratio
``tau = d1 / d2`` (eq. 4). For each range of ``tau`` the distance ``d`` between the voted place and the true
location follows a mixture of a half-normal (votes near the truth) and a uniform long tail (random non-matches):

    f(d) = lambda * sqrt(2) / (sigma sqrt(pi)) exp(-d^2 / (2 sigma^2)) + (1 - lambda) / d_max,   0 <= d <= d_max

    F(d) = lambda * erf(d / (sigma sqrt(2))) + (1 - lambda) * d / d_max

Eq. 7 writes the uniform term as ``(1 - lambda)``; here it is the uniform density over ``[0, d_max]`` (``d_max``:
the diagonal of the bounding box of the map's places), so that ``f`` is a density whose CDF can be fitted.

`fit_vote_model` fits ``sigma`` and ``lambda`` per ``tau`` range by least squares between ``F`` and the empirical
CDF of training votes with ground truth (`placerec.artifacts.votes.training_votes`: query scans with known
poses matched against a places database). The true location is the query's ground-truth position, not its nearest place: the distance to the
nearest place would be quantised to the place spacing, with a point mass at 0 that no half-normal CDF matches.
A range with fewer than ``min_votes`` votes gets ``lambda = 0`` (its votes carry no information).

`VoteModel` is saved as an atomic versioned artifact (kind ``vote-model``) holding the fitted parameters, the
training distances and ratios (so the figure can be redrawn) and its provenance.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, Field

from placerec._version import __version__
from placerec.errors import ArtifactError, ConfigError, ScanDataError, short_repr
from placerec.io.artifact_schema import Member
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params

log = logging.getLogger(__name__)

__all__ = [
    "VoteModelParams",
    "VoteModel",
    "mixture_pdf",
    "mixture_cdf",
    "fit_mixture",
    "fit_vote_model",
    "plot_vote_model",
]

KIND = "vote-model"
FORMAT_VERSION = 1
_SCHEMA = {
    "tau_edges": Member("f", ("n_edges",), finite=True),
    "sigma": Member("f", ("n_ranges",), finite=True, min_value=0),
    "lam": Member("f", ("n_ranges",), finite=True, min_value=0),
    "n_votes": Member("iu", ("n_ranges",), min_value=0),
    "distances": Member("f", ("n_train",), finite=True, min_value=0),
    "taus": Member("f", ("n_train",), finite=True, min_value=0),
}
#: lambda is kept below 1 so that the uniform tail never vanishes (a posterior would otherwise rule out places).
LAMBDA_MAX = 0.999


def _tau_edges(v: list[float]) -> list[float]:
    problem = tau_edges_problem(v)
    if problem is not None:
        raise ValueError(problem)
    return v


#: tau range edges as a parameter: `tau_edges_problem` refuses them naming the first edge out of order
TauEdges = Annotated[list[float], AfterValidator(_tau_edges)]


class VoteModelParams(Params):
    """How votes are binned by ``tau`` and fitted (the paper does not give its ranges)."""

    tau_edges: TauEdges = Field(
        [0.0, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0],
        description="ascending edges of the tau ranges; the last range includes its upper edge",
    )
    min_votes: int = Field(30, ge=2, description="votes a range needs to be fitted (else lambda = 0)")


def tau_edges_problem(edges: Any) -> str | None:
    """Why ``edges`` are no tau range edges (at least 2 values, the first >= 0, strictly increasing), naming the
    first edge out of order; None when they are."""
    v = np.asarray(edges, np.float64).reshape(-1)
    if v.size < 2:
        return f"tau_edges need at least 2 values, got {v.size}"
    if v[0] < 0:
        return f"tau_edges must be >= 0, got {v[0]:g} first"
    back = np.flatnonzero(np.diff(v) <= 0)
    if back.size:
        i = int(back[0]) + 1
        return (
            f"tau_edges must increase strictly: edge {i} is {v[i]:g} after {v[i - 1]:g} "
            f"(got {short_repr(v.tolist())})"
        )
    return None


def mixture_pdf(d: np.ndarray, sigma: float, lam: float, d_max: float) -> np.ndarray:
    """Eq. 7 as a density over ``[0, d_max]`` (see the module docstring)."""
    d = np.asarray(d, np.float64)
    hn = math.sqrt(2.0) / (sigma * math.sqrt(math.pi)) * np.exp(-(d**2) / (2.0 * sigma**2))
    return lam * hn + (1.0 - lam) / d_max


def mixture_cdf(d: np.ndarray, sigma: float, lam: float, d_max: float) -> np.ndarray:
    """The CDF of `mixture_pdf`."""
    from scipy.special import erf

    d = np.asarray(d, np.float64)
    return lam * erf(d / (sigma * math.sqrt(2.0))) + (1.0 - lam) * np.clip(d / d_max, 0.0, 1.0)


def _ecdf(d: np.ndarray, max_points: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """(x, F(x)) of the empirical CDF at most ``max_points`` quantiles (mid-step values)."""
    x = np.sort(np.asarray(d, np.float64))
    n = x.size
    F = (np.arange(n) + 0.5) / n
    if n > max_points:
        pick = np.linspace(0, n - 1, max_points).round().astype(np.int64)
        x, F = x[pick], F[pick]
    return x, F


def fit_mixture(d: np.ndarray, d_max: float) -> tuple[float, float]:
    """(sigma, lambda) minimising the squared difference between `mixture_cdf` and the empirical CDF of ``d``:
    a grid over (log sigma, lambda) for the start, then bounded least squares (scipy)."""
    from scipy.optimize import least_squares

    x, F = _ecdf(d)
    lo, hi = max(1e-3, 1e-4 * d_max), d_max
    sig_grid = np.geomspace(lo, hi, 40)
    lam_grid = np.linspace(0.0, LAMBDA_MAX, 21)
    best = (np.inf, sig_grid[0], 0.0)
    for s in sig_grid:
        for lam in lam_grid:
            r = float(np.sum((mixture_cdf(x, s, lam, d_max) - F) ** 2))
            if r < best[0]:
                best = (r, s, lam)
    res = least_squares(
        lambda p: mixture_cdf(x, math.exp(p[0]), p[1], d_max) - F,
        x0=[math.log(best[1]), best[2]],
        bounds=([math.log(lo), 0.0], [math.log(hi), LAMBDA_MAX]),
    )
    return float(math.exp(res.x[0])), float(res.x[1])


@dataclass
class VoteModel:
    """Fitted ``sigma`` (m) and ``lam`` per ``tau`` range (``tau_edges``, ascending), over ``[0, d_max]``."""

    tau_edges: np.ndarray
    sigma: np.ndarray
    lam: np.ndarray
    d_max: float
    n_votes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    distances: np.ndarray = field(default_factory=lambda: np.zeros(0))
    taus: np.ndarray = field(default_factory=lambda: np.zeros(0))
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.tau_edges = np.asarray(self.tau_edges, np.float64)
        self.sigma = np.asarray(self.sigma, np.float64)
        self.lam = np.asarray(self.lam, np.float64)
        r = self.tau_edges.size - 1
        problem = tau_edges_problem(self.tau_edges) if self.tau_edges.ndim == 1 else "tau_edges must be 1-D"
        if problem is not None:
            raise ConfigError(f"vote model: {problem}")
        if self.sigma.shape != (r,) or self.lam.shape != (r,):
            raise ConfigError(
                f"vote model: {self.tau_edges.size} tau_edges need {r} sigma and lambda values, got "
                f"{self.sigma.shape} and {self.lam.shape}"
            )
        if not (np.all(self.sigma > 0) and np.all((self.lam >= 0) & (self.lam < 1)) and self.d_max > 0):
            raise ConfigError(
                f"vote model: sigma must be > 0, lambda in [0, 1), d_max > 0; got sigma {self.sigma.tolist()}, "
                f"lambda {self.lam.tolist()}, d_max {self.d_max}"
            )
        if self.n_votes.size == 0:
            self.n_votes = np.zeros(r, np.int64)

    @property
    def n_ranges(self) -> int:
        return int(self.sigma.size)

    def range_of(self, tau: np.ndarray) -> np.ndarray:
        """The range index of every ``tau`` (values outside the edges go to the first / last range)."""
        r = np.searchsorted(self.tau_edges, np.asarray(tau, np.float64), side="right") - 1
        return np.clip(r, 0, self.n_ranges - 1)

    def pdf(self, d: np.ndarray, r: int) -> np.ndarray:
        return mixture_pdf(d, float(self.sigma[r]), float(self.lam[r]), self.d_max)

    def cdf(self, d: np.ndarray, r: int) -> np.ndarray:
        return mixture_cdf(d, float(self.sigma[r]), float(self.lam[r]), self.d_max)

    def summary(self) -> list[dict[str, Any]]:
        """One row per range: tau bounds, sigma, lambda and the number of training votes."""
        return [
            {
                "tau": [round(float(self.tau_edges[r]), 4), round(float(self.tau_edges[r + 1]), 4)],
                "sigma_m": round(float(self.sigma[r]), 3),
                "lambda": round(float(self.lam[r]), 4),
                "n_votes": int(self.n_votes[r]),
            }
            for r in range(self.n_ranges)
        ]

    def save(self, path: str | Path) -> None:
        arrays = {
            "tau_edges": self.tau_edges,
            "sigma": self.sigma,
            "lam": self.lam,
            "n_votes": np.asarray(self.n_votes, np.int64),
            "distances": np.asarray(self.distances, np.float32),
            "taus": np.asarray(self.taus, np.float32),
        }
        save_artifact(
            path, KIND, FORMAT_VERSION, arrays, {"d_max": float(self.d_max), "provenance": self.provenance}
        )

    @classmethod
    def load(cls, path: str | Path) -> VoteModel:
        """Read a saved model; `ArtifactError` naming the file when it is not a valid one."""
        arrays, header = load_artifact(path, KIND, (FORMAT_VERSION,), _SCHEMA)
        meta = header["meta"]
        d_max = meta.get("d_max")
        if not isinstance(d_max, int | float) or isinstance(d_max, bool) or not 0 < d_max < math.inf:
            raise ArtifactError(f"{path}: 'd_max' must be a finite number > 0, got {d_max!r}")
        try:
            return cls(
                arrays["tau_edges"],
                arrays["sigma"],
                arrays["lam"],
                float(d_max),
                arrays["n_votes"].astype(np.int64),
                arrays["distances"].astype(np.float64),
                arrays["taus"].astype(np.float64),
                dict(meta.get("provenance") or {}),
            )
        except ConfigError as exc:
            raise ArtifactError(f"{path}: {exc}") from None


def fit_vote_model(
    distances: np.ndarray,
    taus: np.ndarray,
    d_max: float,
    params: VoteModelParams | None = None,
    provenance: dict[str, Any] | None = None,
) -> VoteModel:
    """Fit ``sigma`` and ``lambda`` per tau range to training votes: ``distances`` (m, voted place to the true
    location) and their ``taus``; ``d_max`` bounds the uniform tail (the map's largest place-to-place distance)."""
    params = params or VoteModelParams()
    d = np.asarray(distances, np.float64).ravel()
    t = np.asarray(taus, np.float64).ravel()
    if d.shape != t.shape or not (np.isfinite(d).all() and np.isfinite(t).all()) or (d < 0).any():
        raise ScanDataError(f"votes: {d.size} finite distances >= 0 need as many finite taus, got {t.size}")
    if not d_max > 0:
        raise ScanDataError(f"votes: d_max must be > 0, got {d_max}")
    d = np.minimum(d, d_max)
    edges = np.asarray(params.tau_edges, np.float64)
    proto = VoteModel(edges, np.ones(edges.size - 1), np.zeros(edges.size - 1), float(d_max))
    rng = proto.range_of(t)
    sigma, lam, counts = [], [], []
    for r in range(proto.n_ranges):
        dr = d[rng == r]
        counts.append(dr.size)
        if dr.size < params.min_votes:
            log.warning(
                "vote model: tau range %d has %d votes (< %d): lambda = 0", r, dr.size, params.min_votes
            )
            sigma.append(float(d_max))
            lam.append(0.0)
            continue
        s, la = fit_mixture(dr, float(d_max))
        sigma.append(s)
        lam.append(la)
    prov = {
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "placerec": __version__,
        "params": params.model_dump(mode="json"),
        **(provenance or {}),
    }
    return VoteModel(
        edges, np.asarray(sigma), np.asarray(lam), float(d_max), np.asarray(counts, np.int64), d, t, prov
    )


def plot_vote_model(model: VoteModel, path: str | Path, title: str = "vote model") -> Path:
    """Fitted CDFs (eq. 7) against the empirical CDFs of the training votes, one panel per tau range (Fig. 5)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = model.n_ranges
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.0 * cols, 3.2 * rows), dpi=110, squeeze=False)
    rng = model.range_of(model.taus) if model.taus.size else np.zeros(0, np.int64)
    for r in range(n):
        ax = axes[r // cols][r % cols]
        d = model.distances[rng == r]
        top = float(np.percentile(d, 95)) * 1.2 if d.size else model.d_max
        xs = np.linspace(0.0, max(top, 1.0), 300)
        if d.size:
            x = np.sort(d)
            ax.step(x, np.arange(1, x.size + 1) / x.size, where="post", color="0.3", label="empirical")
        ax.plot(xs, model.cdf(xs, r), color="tab:red", label="fitted (eq. 7)")
        lo, hi = model.tau_edges[r], model.tau_edges[r + 1]
        ax.set_title(
            f"tau [{lo:.2f}, {hi:.2f}): sigma {model.sigma[r]:.2f} m, lambda {model.lam[r]:.2f}, n {d.size}",
            fontsize=8,
        )
        ax.set(xlim=(0, xs[-1]), ylim=(0, 1), xlabel="distance voted place - truth (m)", ylabel="CDF")
        ax.grid(alpha=0.3)
        if r == 0:
            ax.legend(fontsize=7, loc="lower right")
    for r in range(n, rows * cols):
        axes[r // cols][r % cols].axis("off")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
