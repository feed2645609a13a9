"""The evidence figures of a run: one PNG per case `placerec.experiment.evidence.select_cases` (loop mode) or
`select_localize_cases` (localize mode) picked.

Each figure holds the query's and the match's intensity images, one above the other, with the correspondences
the verification was given (`placerec.types.Candidate.matches`) as lines: its inliers
(``verification.inlier_mask``) green, the others faint red; a bird's-eye view of the two clouds, the match's in
its own frame (blue) and the query's moved onto it by the candidate's relative pose (orange: they overlap where
the pose is right); and the candidate's numbers (score, inliers, ICP fitness, the decision, the pose error).
Lines are drawn for the intensity-image pipelines (`placerec.pipelines.visual.VisualFrontend`), whose feature
indices index their description's ``keypoints``; the others get the images (`placerec.image.make_image` with
default parameters) without lines.

The scans are read again after the run (the sequence is random access), each once for all pipelines, and
described again by the pipelines that draw lines (descriptions are deterministic); a figure costs 0.1 to 0.2 s
(docs/evaluation.md).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Sequence as Seq
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from placerec.config import ExperimentConfig
from placerec.errors import ConfigError, ScanDataError
from placerec.experiment.evidence import (
    EvidenceCase,
    RejectionCounts,
    decision_text,
    rejection_counts,
    with_truth,
)
from placerec.experiment.figures import PNG_OPTIONS, _pyplot
from placerec.experiment.preprocessing import preprocessed_scan
from placerec.experiment.run_folder import slug
from placerec.experiment.runner import PipelineRecord
from placerec.image import ImageParams, make_image
from placerec.pipelines.visual import VisualFrontend
from placerec.threads import available_threads
from placerec.types import Candidate, PlaceRecognizer, Scan, Sequence, relative_pose

__all__ = [
    "EVIDENCE_DIR",
    "KIND_WORDS",
    "PipelineEvidence",
    "ClosureView",
    "correspondence_segments",
    "bev_raster",
    "plot_closure",
    "plot_closures",
    "FIGURES_PER_PROCESS",
    "CaseScans",
    "draw_evidence",
    "draw_pair",
]

#: the run folder's subfolder of evidence figures, one folder per pipeline
EVIDENCE_DIR = "evidence"
#: bird's-eye view: half its width (m) around the match's origin, and the side of a cell (m)
BEV_RADIUS_M = 40.0
BEV_CELL_M = 0.25
#: points of a cloud kept for the bird's-eye view (every k-th, in scan order)
BEV_POINTS = 40_000
#: what each gallery kind is called, per mode (loop: `select_cases`, localize: `select_localize_cases`)
KIND_WORDS = {
    "loop": {"accepted": "accepted true closure", "false": "false closure", "missed": "missed revisit"},
    "localize": {"accepted": "localised", "false": "wrong answer", "missed": "no answer"},
}
_MATCH_RGB = np.array([40, 90, 200], np.uint8)
_QUERY_RGB = np.array([245, 130, 20], np.uint8)
_BOTH_RGB = np.array([60, 60, 60], np.uint8)


@dataclass(frozen=True)
class PipelineEvidence:
    """A pipeline's evidence: its ``cases`` (`select_cases`), the figure of each (a path relative to the run
    folder, aligned with ``cases``), the (inlier, all) correspondences each figure draws as lines (None where it
    draws none), and its `RejectionCounts`."""

    label: str
    cases: list[EvidenceCase]
    figures: list[str]
    lines: list[tuple[int, int] | None]
    counts: RejectionCounts


@dataclass(frozen=True, eq=False)
class ClosureView:
    """What one closure figure draws: the 8-bit intensity images of the query and the match, the segments of the
    inlier and outlier correspondences ((K, 2, 2) pixel coordinates on the canvas `plot_closure` stacks: the
    query image above, then a gap of ``gap`` rows, then the match image), the query's and the match's clouds in
    the match frame ((N, 3)), the title and the lines of numbers beside the bird's-eye view."""

    image_query: np.ndarray
    image_match: np.ndarray
    gap: int
    inliers: np.ndarray
    outliers: np.ndarray
    cloud_query: np.ndarray
    cloud_match: np.ndarray
    title: str
    facts: list[str] = field(default_factory=list)


def correspondence_segments(
    matches: np.ndarray,
    inlier_mask: np.ndarray,
    keypoints_query: np.ndarray,
    keypoints_match: np.ndarray,
    offset: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(inlier, outlier) segments, each (K, 2, 2): from the query keypoint of each pair of ``matches`` ((M, 2)
    feature indices) to its match keypoint shifted down by ``offset`` rows; ``inlier_mask`` (M,) splits them.
    `ScanDataError` when a feature index is out of range or the mask does not fit the pairs."""
    pairs = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    mask = np.asarray(inlier_mask, dtype=bool).reshape(-1)
    kq = np.asarray(keypoints_query, np.float64).reshape(-1, 2)
    km = np.asarray(keypoints_match, np.float64).reshape(-1, 2)
    if mask.size != pairs.shape[0]:
        raise ScanDataError(f"an inlier mask of {mask.size} for {pairs.shape[0]} correspondences")
    if pairs.size and (pairs.min() < 0 or pairs[:, 0].max() >= len(kq) or pairs[:, 1].max() >= len(km)):
        raise ScanDataError(
            f"correspondences index {len(kq)} query and {len(km)} match keypoints, got indices up to"
            f" {pairs.max(axis=0).tolist()}"
        )
    seg = np.stack([kq[pairs[:, 0]], km[pairs[:, 1]] + [0.0, offset]], axis=1)
    return seg[mask], seg[~mask]


def bev_raster(cloud_match: np.ndarray, cloud_query: np.ndarray, radius: float, cell: float) -> np.ndarray:
    """An RGB (H, W, 3) top view of two clouds within ``radius`` m of the origin in ``cell`` m cells (row 0 at
    +y): match cells blue, query cells orange, cells of both dark grey, empty white."""
    n = int(np.ceil(2 * radius / cell))
    occupied = []
    for cloud in (cloud_match, cloud_query):
        xy = np.asarray(cloud, np.float64).reshape(-1, 3)[:, :2]
        ij = np.floor((xy + radius) / cell).astype(np.int64)
        ok = ((ij >= 0) & (ij < n)).all(axis=1)
        grid = np.zeros((n, n), dtype=bool)
        grid[n - 1 - ij[ok, 1], ij[ok, 0]] = True
        occupied.append(grid)
    rgb = np.full((n, n, 3), 255, np.uint8)
    rgb[occupied[0]] = _MATCH_RGB
    rgb[occupied[1]] = _QUERY_RGB
    rgb[occupied[0] & occupied[1]] = _BOTH_RGB
    return rgb


def plot_closure(view: ClosureView, path: Path) -> Path:
    """Draw ``view`` (see `ClosureView`) into the PNG ``path``: the image pair across the top, the bird's-eye
    view and the numbers under it. Axes are placed by hand (no tight layout): a gallery draws many figures."""
    from matplotlib.collections import LineCollection

    plt = _pyplot()
    hq, wq = view.image_query.shape
    hm, wm = view.image_match.shape
    width = max(wq, wm)
    canvas = np.full((hq + view.gap + hm, width), 255, np.uint8)
    canvas[:hq, :wq] = view.image_query
    canvas[hq + view.gap :, :wm] = view.image_match
    w_in, bev_in, pad = 10.0, 3.6, 0.45
    top_in = max(w_in * canvas.shape[0] / width, 0.6)
    h_in = top_in + bev_in + 3 * pad
    fig = plt.figure(figsize=(w_in, h_in), dpi=80)
    ax = fig.add_axes((0.01, (bev_in + 2 * pad) / h_in, 0.98, top_in / h_in))
    ax.imshow(canvas, cmap="gray", aspect="auto", interpolation="nearest")
    if len(view.outliers):
        ax.add_collection(LineCollection(list(view.outliers), colors="#d62728", lw=0.5, alpha=0.25))
    if len(view.inliers):
        ax.add_collection(LineCollection(list(view.inliers), colors="#2ca02c", lw=0.8))
    ax.set_axis_off()
    fig.text(0.01, 1 - 0.35 * pad / h_in, view.title, fontsize=9, va="top")
    bev = fig.add_axes((0.6 / w_in, pad / h_in, bev_in / w_in, bev_in / h_in))
    r = BEV_RADIUS_M
    bev.imshow(bev_raster(view.cloud_match, view.cloud_query, r, BEV_CELL_M), extent=(-r, r, -r, r))
    ticks = np.linspace(-r, r, 5)
    bev.set_xticks(ticks)
    bev.set_yticks(ticks)
    bev.tick_params(labelsize=7)
    bev.set_title("blue: match, orange: query moved by the pose (m)", fontsize=8)
    fig.text(
        (bev_in + 1.2) / w_in,
        (bev_in + pad) / h_in,
        "\n".join(view.facts),
        va="top",
        fontsize=9,
        family="monospace",
    )
    fig.savefig(path, pil_kwargs=PNG_OPTIONS)
    plt.close(fig)
    return path


def _bev_points(xyz: np.ndarray) -> np.ndarray:
    """The finite, non-zero points of a scan within the bird's-eye view, at most `BEV_POINTS` of them."""
    p = np.asarray(xyz, np.float32)
    ok = np.isfinite(p).all(axis=1) & (np.abs(p[:, :2]) < BEV_RADIUS_M * 1.5).all(axis=1) & p.any(axis=1)
    p = p[ok]
    return p[:: max(1, -(-len(p) // BEV_POINTS))]


def _moved(cloud: np.ndarray, T: np.ndarray) -> np.ndarray:
    return cloud @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)


def _num(value: float | None, fmt: str) -> str:
    """``value`` formatted, ``-`` when it is None or NaN (a statistic that was not computed)."""
    return "-" if value is None or not np.isfinite(value) else format(value, fmt)


def _facts(case: EvidenceCase, pose_source: str) -> list[str]:
    """The lines of numbers beside a closure's bird's-eye view."""
    c = case.candidate
    lines = [
        f"query {case.query_id}  match {case.match_id}",
        f"right place: {'yes' if case.correct else 'no'} (ground truth)",
        f"decision: {case.decision}",
    ]
    if np.isfinite(case.distance_m):
        lines.insert(2, f"scans {case.distance_m:.1f} m apart (ground truth)")
    if c is None:
        return [*lines, "no candidate: the revisited scan,", "posed by the ground truth"]
    lines.append(f"rank {case.rank + 1}  score {c.score:.4g}")
    v = c.verification
    if v is not None:
        if v.correspondences:
            inl = "-" if v.inliers is None else str(v.inliers)
            lines.append(f"inliers {inl} of {v.correspondences} pairs")
        lines.append(f"fitness {_num(v.fitness, '.3f')}  rmse {_num(v.rmse, '.3f')} m")
        lines.append(f"verified score {v.score:.3f}")
    elif c.inliers is not None:
        lines.append(f"inliers {c.inliers}")
    if np.isfinite(case.translation_m):
        lines.append(f"pose error {case.translation_m:.2f} m / {case.rotation_deg:.2f} deg")
    lines.append(f"pose: {pose_source}")
    return lines


def _line_pairs(rec: PlaceRecognizer | None, case: EvidenceCase) -> tuple[np.ndarray, np.ndarray] | None:
    """The (matches, inlier mask) a case's figure draws as lines: an intensity-image pipeline's verified
    candidate with its correspondences; None otherwise."""
    c = case.candidate
    if not isinstance(rec, VisualFrontend) or c is None or c.matches is None or c.verification is None:
        return None
    mask = c.verification.inlier_mask
    return None if mask is None else (c.matches, mask)


def _draws_lines(rec: PlaceRecognizer | None, case: EvidenceCase) -> bool:
    return _line_pairs(rec, case) is not None


def _image_params(rec: PlaceRecognizer | None) -> ImageParams:
    return rec.params.image if isinstance(rec, VisualFrontend) else ImageParams()


def _recognizers(
    records: list[PipelineRecord], cases: list[list[EvidenceCase]], given: Seq[PlaceRecognizer] | None
) -> list[PlaceRecognizer | None]:
    """The recognizers the figures describe scans with (``given``, aligned with ``records``); without them each
    intensity-image pipeline with a case is built again from its record. None for the others, and for a record
    whose pipeline is no registered name or importable class (made by hand): its figures draw no lines."""
    from placerec.recognizer import make_pipeline, pipeline_class

    if given is not None:
        return list(given)
    out: list[PlaceRecognizer | None] = []
    for record, cs in zip(records, cases, strict=True):
        try:
            visual = bool(cs) and issubclass(pipeline_class(record.pipeline), VisualFrontend)
        except ConfigError:
            visual = False
        out.append(make_pipeline(record.pipeline, record.params) if visual else None)
    return out


@dataclass(frozen=True, eq=False)
class CaseScans:
    """Where the scans and true poses of a run's cases come from: ``queries``, the sequence a case's query id
    indexes, and ``matches``, the one its match id indexes (the same sequence in loop mode; the map in localize
    mode). Both have poses."""

    queries: Sequence
    matches: Sequence

    @property
    def match_side(self) -> int:
        """The side (0: queries) a match id's scan is kept under: one per sequence, so a loop run reads each scan
        once."""
        return 0 if self.matches is self.queries else 1

    @property
    def mode(self) -> str:
        """``loop`` (one sequence) or ``localize`` (queries against a map)."""
        return "loop" if self.matches is self.queries else "localize"

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(query poses, match poses)."""
        assert self.queries.poses is not None and self.matches.poses is not None  # the reports check them
        return self.queries.poses, self.matches.poses


@dataclass
class _Shown:
    """What the figures show of each scan, read once for every pipeline and keyed by (side, index) (side 0 for
    the queries' sequence, `CaseScans.match_side` for the matches'): bird's-eye points, 8-bit images by image
    parameters (as JSON), keypoints by front end key (None for a scan the front end cannot describe)."""

    points: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    images: dict[tuple[str, tuple[int, int]], np.ndarray] = field(default_factory=dict)
    keypoints: dict[tuple[str, tuple[int, int]], np.ndarray | None] = field(default_factory=dict)

    def add(self, at: tuple[int, int], scan: Scan, uses: list[tuple[PlaceRecognizer | None, bool]]) -> None:
        """Keep what the figures show of ``scan`` (at (side, index)) for each (recognizer, draws lines) of
        ``uses``."""
        self.points[at] = _bev_points(scan.xyz)
        for rec, lines in uses:
            params = _image_params(rec)
            key = params.model_dump_json()
            if (key, at) not in self.images:
                self.images[key, at] = make_image(scan, params).image
            if lines and rec is not None and (rec.frontend_key, at) not in self.keypoints:
                try:
                    self.keypoints[rec.frontend_key, at] = np.asarray(rec.describe(scan)["keypoints"])
                except ScanDataError:
                    self.keypoints[rec.frontend_key, at] = None


def _read_shown(
    cfg: ExperimentConfig,
    scans: CaseScans,
    recs: list[PlaceRecognizer | None],
    cases: list[list[EvidenceCase]],
) -> _Shown:
    """`_Shown` of every scan a case shows, each read once."""
    uses: dict[tuple[int, int], list[tuple[PlaceRecognizer | None, bool]]] = {}
    for rec, cs in zip(recs, cases, strict=True):
        for c in cs:
            for at in ((0, c.query_id), (scans.match_side, c.match_id)):
                uses.setdefault(at, []).append((rec, _draws_lines(rec, c)))
    shown = _Shown()
    for side, i in sorted(uses):
        seq = scans.queries if side == 0 else scans.matches
        shown.add((side, i), preprocessed_scan(seq, i, cfg.preprocess)[0], uses[side, i])
    return shown


def draw_pair(
    label: str,
    kind: str,
    scan_query: Scan,
    scan_match: Scan,
    candidate: Candidate | None,
    rec: PlaceRecognizer,
    path: Path,
    threshold: float,
    correct: bool,
    T_match_query_truth: np.ndarray | None = None,
    ids: tuple[int, int] = (1, 0),
) -> ClosureView:
    """The evidence figure of one closure outside a run (e.g. the docs' figures): ``candidate``, the answer of
    ``rec`` for ``scan_query`` against ``scan_match`` (None: it gave none), drawn as a loop-mode ``kind`` (one of
    `KINDS`) case of pipeline ``label`` judged at ``threshold``; ``correct`` says whether it is the right place,
    ``T_match_query_truth`` (when known) gives its pose error, and without a candidate the overlay's pose.
    ``ids``: the (query, match) ids the figure names. Returns the view drawn into ``path``."""
    q, m = ids
    # the match at the origin, the query where the truth puts it
    match_poses = np.tile(np.eye(4), (m + 1, 1, 1))
    query_poses = np.tile(np.eye(4), (q + 1, 1, 1))
    if T_match_query_truth is not None:
        query_poses[q] = T_match_query_truth
    rank = -1 if candidate is None else 0
    case = EvidenceCase(kind, q, m, rank, candidate, decision_text(candidate, threshold), correct)
    if T_match_query_truth is not None:
        case = with_truth(case, match_poses, query_poses)
    shown = _Shown()
    lines = _draws_lines(rec, case)
    shown.add((0, q), scan_query, [(rec, lines)])
    shown.add((1, m), scan_match, [(rec, lines)])
    view = _view(label, case, rec, shown, 1, (query_poses, match_poses), KIND_WORDS["loop"])
    plot_closure(view, path)
    return view


def _view(
    label: str,
    case: EvidenceCase,
    rec: PlaceRecognizer | None,
    shown: _Shown,
    match_side: int,
    poses: tuple[np.ndarray, np.ndarray],
    words: dict[str, str],
) -> ClosureView:
    """The `ClosureView` of one case of pipeline ``label``; ``poses``: (query poses, match poses), ``words``: what
    each kind is called (`KIND_WORDS`)."""
    q, m = (0, case.query_id), (match_side, case.match_id)
    key = _image_params(rec).model_dump_json()
    image_q = shown.images[key, q]
    gap = max(4, image_q.shape[0] // 4)
    inl = outl = np.zeros((0, 2, 2))
    lines = _line_pairs(rec, case)
    if lines is not None and rec is not None:
        kq, km = shown.keypoints[rec.frontend_key, q], shown.keypoints[rec.frontend_key, m]
        if kq is not None and km is not None:
            inl, outl = correspondence_segments(*lines, kq, km, image_q.shape[0] + gap)
    T, source = _pose_for(case, *poses)
    title = f"{label}: {words[case.kind]}, query {q[1]} (top) / match {m[1]} (bottom): {case.decision}"
    if lines is not None:
        title += f"; {len(inl)} inliers (green) of {len(inl) + len(outl)} pairs"
    return ClosureView(
        image_q,
        shown.images[key, m],
        gap,
        inl,
        outl,
        _moved(shown.points[q], T),
        shown.points[m],
        title,
        _facts(case, source),
    )


def draw_evidence(
    cfg: ExperimentConfig,
    run: Path,
    records: list[PipelineRecord],
    cases: list[list[EvidenceCase]],
    scans: CaseScans,
    recognizers: Seq[PlaceRecognizer] | None = None,
) -> list[PipelineEvidence]:
    """Each pipeline's `PipelineEvidence`, its ``cases`` (`select_cases` or `select_localize_cases`, aligned with
    ``records``) drawn under ``run/evidence/<pipeline>/``; ``recognizers`` (aligned with ``records``) describe
    the scans of the pipelines that draw lines; without them those pipelines are built again from their
    records."""
    recs = _recognizers(records, cases, recognizers)
    shown = _read_shown(cfg, scans, recs, cases)
    out, jobs = [], []
    for record, rec, cs in zip(records, recs, cases, strict=True):
        folder = run / EVIDENCE_DIR / slug(record.label)
        folder.mkdir(parents=True, exist_ok=True)
        names, lines = [], []
        for case in cs:
            name = f"{case.kind}_{case.query_id:06d}_{case.match_id:06d}.png"
            view = _view(
                record.label, case, rec, shown, scans.match_side, scans.poses(), KIND_WORDS[scans.mode]
            )
            jobs.append((view, folder / name))
            names.append(f"{EVIDENCE_DIR}/{slug(record.label)}/{name}")
            drawn = len(view.inliers) + len(view.outliers)
            lines.append((len(view.inliers), drawn) if drawn else None)
        out.append(PipelineEvidence(record.label, cs, names, lines, rejection_counts(record.candidates)))
    plot_closures(jobs)
    return out


#: a drawing process takes ~1.5 s to start (imports) and a figure ~0.2 s: one per this many figures at most
FIGURES_PER_PROCESS = 20


def plot_closures(jobs: Seq[tuple[ClosureView, Path]], processes: int | None = None) -> None:
    """`plot_closure` of each (view, path): on ``processes`` spawned processes (None: one per
    `FIGURES_PER_PROCESS` figures, at most `placerec.threads.available_threads`), in this one when that is
    fewer than 2. Each figure is drawn as this process draws it (the same bytes)."""
    if processes is None:
        processes = min(available_threads(), len(jobs) // FIGURES_PER_PROCESS)
    if processes < 2:
        for view, path in jobs:
            plot_closure(view, path)
        return
    with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn")) as pool:
        for done in [pool.submit(plot_closure, view, path) for view, path in jobs]:
            done.result()


def _pose_for(case: EvidenceCase, query_poses: np.ndarray, match_poses: np.ndarray) -> tuple[np.ndarray, str]:
    """The pose that moves the query onto the match in the bird's-eye view, and where it comes from."""
    T = case.T_match_query
    if case.candidate is None:
        return relative_pose(match_poses[case.match_id], query_poses[case.query_id]), "ground truth"
    if T is None or not np.isfinite(T).all():
        return np.eye(4), "none (clouds in their own frames)"
    if case.candidate.accepted is False:
        return np.asarray(T, np.float64), "the candidate's, as rejected"
    return np.asarray(T, np.float64), "the candidate's estimate"
