"""Training pairs for SuperPoint: simulated intensity images, ground-truth correspondences, detector labels.

* **Pairs.** Simulated sequences of worlds and seeds not used for evaluation (default world seeds 100-103, and
  104 for validation; the evaluation configs use 0-9, ``tools/eval_features.py`` holds out 200-203). In each,
  anchor scans spread along the route are paired with a scan 1-8 m further along it, and scans on a revisit with
  the nearest scan of the earlier pass (the same place seen again, possibly from the other direction). Images are
  formed as the pipelines form them (``preprocess``, then `placerec.image.make_image`).
* **Ground truth.** Pixel correspondences of each pair from the 3D points and poses, visibility and occlusion
  included (`placerec.image.correspondence`).
* **Detector supervision: repeatability of 3D points across views.** Corner candidates (local maxima of the
  Shi-Tomasi minimum eigenvalue) of one image are kept when their 3D point, seen from the other pose, falls
  within ``repeat_px`` of a candidate of the other image. Each 8x8 cell's label is its strongest kept candidate
  (one of 64 positions), else the dustbin (`cell_labels`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from placerec.config import DatasetConfig, SimulatorConfig, experiment_preprocess
from placerec.errors import ConfigError
from placerec.features.superpoint.arch import CELL, DETECTOR_CHANNELS
from placerec.hashing import stable_hash
from placerec.params import Params
from placerec.preprocess import PreprocessParams

log = logging.getLogger(__name__)

__all__ = [
    "PairData",
    "TrainingData",
    "corner_candidates",
    "repeatable",
    "cell_labels",
    "build_pairs",
    "data_fingerprint",
]


class TrainingData(Params):
    """Which simulated pairs to train on."""

    worlds: list[str] = Field(default_factory=lambda: ["campus", "industrial", "town"])
    sensors: list[str] = Field(default_factory=lambda: ["os1-64", "hdl64"], description="64-beam sensors")
    seeds: list[int] = Field(default_factory=lambda: [100, 101, 102])
    validation_seed: int = Field(104, description="world seed of the validation pairs (not trained on)")
    anchors: int = Field(30, ge=1, description="anchor scans per sequence, spread along the route")
    validation_anchors: int = Field(6, ge=1, description="anchor scans per validation sequence")
    offset_m: list[float] = Field(
        default_factory=lambda: [1.0, 8.0],
        min_length=2,
        max_length=2,
        description="partner distance along the route (m)",
    )
    revisit_pairs: int = Field(10, ge=0, description="revisit pairs per sequence (most)")
    validation_revisit_pairs: int = Field(2, ge=0, description="revisit pairs per validation sequence")
    max_dist: float = Field(0.3, gt=0, description="m; 3D distance of corresponding points")
    keep_correspondences: int = Field(4000, gt=0, description="correspondences stored per pair")
    candidates: int = Field(1000, gt=0, description="corner candidates per image")
    repeat_px: float = Field(2.0, gt=0, description="px; a candidate is repeatable within this")
    preprocess: PreprocessParams = Field(default_factory=experiment_preprocess)
    workers: int = Field(2, ge=1, description="processes rendering the sequences")


# ----------------------------------------------------------------------------- labels


def corner_candidates(image: np.ndarray, valid: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``n`` strongest local maxima (3x3) of the Shi-Tomasi minimum eigenvalue on valid pixels: (K, 2)
    ``(u, v)`` int and (K,) responses."""
    r = cv2.cornerMinEigenVal(image, 3, ksize=3)
    peak = (r >= cv2.dilate(r, np.ones((3, 3), np.uint8))) & valid & (r > 0)
    v, u = np.nonzero(peak)
    order = np.argsort(-r[v, u], kind="stable")[:n]
    return np.stack([u[order], v[order]], axis=1), r[v[order], u[order]].astype(np.float32)


def repeatable(
    cand_a: np.ndarray, cand_b: np.ndarray, map_ab: np.ndarray, width_b: int, radius: float
) -> np.ndarray:
    """Mask of A's candidates whose pixel in B (``map_ab`` (H, W, 2), -1 where the point is not seen in B) lies
    within ``radius`` px of one of B's candidates (columns wrap around)."""
    out = np.zeros(len(cand_a), bool)
    if len(cand_a) == 0 or len(cand_b) == 0:
        return out
    target = map_ab[cand_a[:, 1], cand_a[:, 0]]
    seen = target[:, 0] >= 0
    wrapped = np.concatenate([cand_b + [s * width_b, 0] for s in (-1, 0, 1)]).astype(np.float64)
    d, _ = cKDTree(wrapped).query(target[seen].astype(np.float64))
    out[seen] = d <= radius
    return out


def cell_labels(uv: np.ndarray, response: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H/8, W/8) int64 targets: in each cell the position ``8 * dy + dx`` of its strongest keypoint, else 64."""
    labels = np.full((height // CELL, width // CELL), DETECTOR_CHANNELS - 1, np.int64)
    if len(uv):
        order = np.argsort(response, kind="stable")  # the strongest is written last
        u, v = uv[order, 0], uv[order, 1]
        labels[v // CELL, u // CELL] = (v % CELL) * CELL + (u % CELL)
    return labels


# ----------------------------------------------------------------------------- pairs


@dataclass
class PairData:
    """One training pair: 8-bit images, mutual pixel correspondences (M, 2) each, repeatable keypoints with
    their responses, and where it comes from."""

    image_a: np.ndarray
    image_b: np.ndarray
    uv_a: np.ndarray
    uv_b: np.ndarray
    kp_a: np.ndarray
    resp_a: np.ndarray
    kp_b: np.ndarray
    resp_b: np.ndarray
    label: str


def _pair_indices(seq: Any, cfg: TrainingData, rng: np.random.Generator) -> list[tuple[int, int]]:
    pos = np.asarray(seq.poses)[:, :3, 3]
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    pairs = []
    for i in np.unique(np.linspace(0, len(pos) - 1, cfg.anchors).round().astype(int)):
        d = rng.uniform(cfg.offset_m[0], cfg.offset_m[1])
        ahead = along[i] + d if along[i] + d <= along[-1] else along[i] - d
        pairs.append((int(i), int(np.argmin(np.abs(along - ahead)))))
    revisits = []
    for r in seq.revisits:
        for i in range(r.start, r.stop):
            ref = np.arange(r.ref_start, r.ref_stop + 1)
            j = int(ref[np.argmin(np.linalg.norm(pos[ref] - pos[i], axis=1))])
            revisits.append((i, j))
    if revisits and cfg.revisit_pairs:
        pick = rng.choice(len(revisits), min(cfg.revisit_pairs, len(revisits)), replace=False)
        pairs.extend(revisits[k] for k in sorted(pick))
    return [(i, j) for i, j in pairs if i != j]


def _sequence_pairs(job: tuple[dict[str, Any], dict[str, Any], int, str]) -> list[PairData]:
    """Render one sequence's pairs (runs in a worker process)."""
    from placerec.experiment.datasets import open_dataset
    from placerec.image import make_image
    from placerec.image.correspondence import pixel_correspondences, pixel_points
    from placerec.preprocess import preprocess_scan

    spec, data_cfg, seed, label = job
    cfg = TrainingData.model_validate(data_cfg)
    seq = open_dataset(DatasetConfig.model_validate(spec))
    rng = np.random.default_rng(seed)
    pairs = _pair_indices(seq, cfg, rng)
    pp = cfg.preprocess
    views: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def view(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if i not in views:
            scan = preprocess_scan(seq[i], pp, keep_organized=True)
            img = make_image(scan)
            pts = pixel_points(img, scan)
            views[i] = (
                img.image,
                pts,
                *corner_candidates(img.image, np.isfinite(pts[..., 0]), cfg.candidates),
            )
        return views[i]

    out = []
    poses = np.asarray(seq.poses)
    for i, j in pairs:
        (ia, pa, ca, ra), (ib, pb, cb, rb) = view(i), view(j)
        if ia.shape[0] != 64 or ib.shape[0] != 64:
            raise ConfigError(
                f"superpoint training: {label} gives {ia.shape[0]}-row images; use 64-beam sensors"
            )
        a_to_b = np.linalg.inv(poses[j]) @ poses[i]
        dense = [
            pixel_correspondences(p, q, T, cfg.max_dist, mutual=False)
            for p, q, T in ((pa, pb, a_to_b), (pb, pa, np.linalg.inv(a_to_b)))
        ]
        maps = []
        for c, shape in zip(dense, (ia.shape, ib.shape), strict=True):
            m = np.full(shape + (2,), -1, np.int32)
            m[c.uv_a[:, 1], c.uv_a[:, 0]] = c.uv_b
            maps.append(m)
        keep_a = repeatable(ca, cb, maps[0], ib.shape[1], cfg.repeat_px)
        keep_b = repeatable(cb, ca, maps[1], ia.shape[1], cfg.repeat_px)
        mutual = pixel_correspondences(pa, pb, a_to_b, cfg.max_dist, mutual=True)
        sel = rng.permutation(len(mutual))[: cfg.keep_correspondences]
        out.append(
            PairData(
                ia,
                ib,
                mutual.uv_a[sel].astype(np.int16),
                mutual.uv_b[sel].astype(np.int16),
                ca[keep_a].astype(np.int16),
                ra[keep_a],
                cb[keep_b].astype(np.int16),
                rb[keep_b],
                f"{label}[{i}-{j}]",
            )
        )
    return out


def _jobs(cfg: TrainingData, split: str) -> list[tuple[dict[str, Any], dict[str, Any], int, str]]:
    seeds = cfg.seeds
    if split == "validation":
        seeds = [cfg.validation_seed]
        cfg = cfg.model_copy(
            update={"anchors": cfg.validation_anchors, "revisit_pairs": cfg.validation_revisit_pairs}
        )
    jobs = []
    for w in cfg.worlds:
        for s in cfg.sensors:
            for seed in seeds:
                spec = DatasetConfig(
                    source="simulator", simulator=SimulatorConfig(world=w, sensor=s, seed=seed)
                )
                label = f"{w}/{s}/seed{seed}"
                jobs.append((spec.model_dump(mode="json"), cfg.model_dump(mode="json"), seed, label))
    return jobs


def data_fingerprint(cfg: TrainingData) -> str:
    """Hash of the data settings and the simulator's code: the cache key of the rendered pairs."""
    from placerec.experiment.datasets import dataset_fingerprint

    sim = dataset_fingerprint(DatasetConfig(source="simulator"))
    return stable_hash([cfg.model_dump(mode="json", exclude={"workers"}), sim])


_PAIR_FIELDS = ("image_a", "image_b", "uv_a", "uv_b", "kp_a", "resp_a", "kp_b", "resp_b")


def build_pairs(
    cfg: TrainingData, cache: str | Path | None, progress: bool = False
) -> dict[str, list[PairData]]:
    """``{"train": [...], "validation": [...]}`` pairs, rendered in ``cfg.workers`` processes, or read from
    ``cache`` (keyed by `data_fingerprint`)."""
    path = None if cache is None else Path(cache) / f"pairs_{data_fingerprint(cfg)}.npz"
    if path is not None and path.is_file():
        return _read_pairs(path)
    out: dict[str, list[PairData]] = {}
    for split in ("train", "validation"):
        jobs = _jobs(cfg, split)
        res: list[PairData] = []
        with ProcessPoolExecutor(cfg.workers) as pool:
            it: Iterable[list[PairData]] = pool.map(_sequence_pairs, jobs)
            if progress:
                from rich.progress import track

                it = track(it, total=len(jobs), description=f"rendering {split} pairs")
            for r in it:
                res.extend(r)
        out[split] = res
    if path is not None:
        _write_pairs(path, out)
    return out


def _write_pairs(path: Path, pairs: dict[str, list[PairData]]) -> None:
    from placerec.io.atomic import atomic_write

    arrays: dict[str, Any] = {}
    for split, items in pairs.items():
        arrays[f"{split}.labels"] = np.array([p.label for p in items])
        for k, p in enumerate(items):
            for f in _PAIR_FIELDS:
                arrays[f"{split}.{k}.{f}"] = getattr(p, f)
    with atomic_write(path) as fh:
        np.savez(fh, **arrays)


def _read_pairs(path: Path) -> dict[str, list[PairData]]:
    with np.load(path, allow_pickle=False) as z:
        out = {}
        for split in ("train", "validation"):
            labels = [str(s) for s in z[f"{split}.labels"]]
            out[split] = [
                PairData(**{f: z[f"{split}.{k}.{f}"] for f in _PAIR_FIELDS}, label=lab)
                for k, lab in enumerate(labels)
            ]
    log.info("training pairs from the cache %s", path)
    return out
