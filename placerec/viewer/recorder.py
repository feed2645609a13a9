"""`Recorder`: what a run logs to Rerun, one method per event (docs/viewer.md lists the entity paths).

Every event is logged on the ``scan`` timeline (the scan's index in the run; SLAM and relocalisation number their
scans the same way) and, when the scan has a time stamp, on ``scan_time``; the ISHOT posterior also on
``ishot_batch`` (one step per batch of matched keypoints, counted over the whole run). Clouds are subsampled to
``max_points`` points, images are JPEG-compressed: the cost per scan is measured in docs/viewer.md.

This module imports ``rerun`` at its top: only `placerec.viewer.recorder` (asked for a recording) imports it.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import rerun as rr

from placerec.io.atomic import atomic_write
from placerec.types import REJECTIONS, Candidate, Description, PlaceRecognizer, Scan, valid_points

if TYPE_CHECKING:
    from placerec.pipelines.probabilistic_voting import PosteriorStep
    from placerec.viewer.target import ViewerTarget

__all__ = ["Recorder", "closure_kind", "candidate_text"]

#: colours (RGB) of the accepted and the rejected loop edges, of inlier correspondences, of the aligned clouds
ACCEPTED, REJECTED = (40, 200, 80), (230, 60, 50)
#: an injected (false) loop of `placerec slam`'s robustness test
INJECTED = (200, 60, 220)
MATCH_CLOUD, QUERY_CLOUD = (150, 150, 150), (255, 140, 0)
#: viridis at 5 stops: the scan's intensity colours
_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float32)
#: a time stamp above this (s) is a date (Unix time), below it a time since the sequence's start
_EPOCH_S = 1e8


def closure_kind(top1: Candidate | None, threshold: float | None) -> str | None:
    """The loop edge a query's best candidate makes in a run: ``accepted`` when verification accepted it (for a
    pipeline that does not verify: its score reaches ``threshold``), ``rejected`` when verification rejected it,
    None otherwise (no candidate, or neither verified nor judged by a threshold)."""
    if top1 is None:
        return None
    if top1.accepted is not None:
        return "accepted" if top1.accepted else "rejected"
    if threshold is not None and top1.score >= threshold:
        return "accepted"
    return None


def candidate_text(c: Candidate, rank: int) -> str:
    """A candidate's verification as a few markdown lines: match, scores, inliers, ICP fitness, the decision."""
    lines = [f"**rank {rank}**: query {c.query_id} -> match {c.match_id}, score {c.score:.4g}"]
    if c.retrieval_score is not None:
        lines.append(f"retrieval score {c.retrieval_score:.4g}")
    v = c.verification
    if v is not None:
        inl = "-" if v.inliers is None else str(v.inliers)
        lines.append(f"inliers {inl} of {v.correspondences} correspondences")
        lines.append(f"fitness {v.fitness:.3g}, rmse {v.rmse:.3g} m, residual {v.residual:.3g} m^2")
    elif c.inliers is not None:
        lines.append(f"inliers {c.inliers}")
    if c.accepted is None:
        lines.append("not verified")
    elif c.accepted:
        lines.append("**accepted**")
    else:
        lines.append(f"**rejected**: {REJECTIONS.get(c.rejection or '', 'no reason given')}")
    return "  \n".join(lines)


def _colours(values: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 viridis colours of ``values`` scaled to their 1st..99th percentile."""
    if values.size == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(values, [1, 99])
    t = np.clip((values - lo) / max(float(hi - lo), 1e-9), 0, 1) * (len(_STOPS) - 1)
    i = np.minimum(t.astype(np.int64), len(_STOPS) - 2)
    f = (t - i)[:, None]
    return (_STOPS[i] * (1 - f) + _STOPS[i + 1] * f).astype(np.uint8)


def _subsample(n: int, most: int) -> np.ndarray:
    """Indices of at most ``most`` of ``n`` items, evenly spread (deterministic)."""
    return np.arange(n) if n <= most else np.linspace(0, n - 1, most).astype(np.int64)


def _part(label: str) -> str:
    """A pipeline's label as one part of an entity path (``/``, ``:``, spaces escaped as Rerun wants them)."""
    return str(rr.escape_entity_path_part(label))


def _moved(xyz: np.ndarray, T: np.ndarray) -> np.ndarray:
    return xyz @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)


def _transform(T: np.ndarray) -> rr.Transform3D:
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


def _jpeg(image: np.ndarray) -> bytes:
    """An 8-bit image as JPEG (OpenCV's encoder: about 3x faster than Rerun's own ``compress``)."""
    import cv2

    _, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return data.tobytes()


def _unjpeg(data: bytes) -> np.ndarray:
    import cv2

    return np.asarray(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE))


def _encoded(data: bytes) -> rr.EncodedImage:
    return rr.EncodedImage(contents=data, media_type="image/jpeg")


def _stacked(top: np.ndarray, bottom: np.ndarray) -> np.ndarray:
    """Two 8-bit images one above the other (the narrower padded with black on the right)."""
    w = max(top.shape[1], bottom.shape[1])
    pad = [np.pad(im, ((0, 0), (0, w - im.shape[1]))) for im in (top, bottom)]
    return np.vstack(pad)


def _spawn(stream: rr.RecordingStream) -> None:
    """Start the Rerun viewer (`placerec.viewer.viewer_executable`: Rerun looks for it on PATH, so a viewer
    found beside Python is put on PATH for the start only)."""
    import os

    from placerec.viewer.target import viewer_executable

    exe = viewer_executable()
    old = os.environ.get("PATH", "")
    if exe is not None:
        os.environ["PATH"] = os.pathsep.join([str(exe.parent), old])
    try:
        stream.spawn(connect=False)
    finally:
        os.environ["PATH"] = old


class _Growing:
    """Items shown as one entity that grows during the run (loop edges, fixes). Re-logging all of them at every
    addition would make the file grow with their square, so the entity is logged again once it has grown by 5 %
    (at least one item) since it was last logged, and at the end of the recording: the file grows linearly."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        self.logged = 0

    def add(self, item: Any) -> bool:
        """Add ``item``; True when the entity is due to be logged again."""
        self.items.append(item)
        return len(self.items) - self.logged >= max(1, self.logged // 20)


class Recorder:
    """Logs a run's events to one Rerun recording (module docstring); made by `placerec.viewer.recording`.
    ``max_points``, ``every_candidate``: `placerec.viewer.ViewerTarget`'s."""

    def __init__(self, stream: rr.RecordingStream, max_points: int, every_candidate: bool = False) -> None:
        self.rr = stream
        self.max_points = max_points
        #: the pair and alignment of every candidate, not only of the best and the accepted ones
        self.every_candidate = every_candidate
        self.index = -1
        #: where candidates' match ids point: ``scan`` (the run's own scans) or ``map`` (`remember`-ed scans)
        self.matches_in = "scan"
        # (space, scan index) -> every other point of its logged cloud (sensor frame) / its position (world): what
        # the alignments and fixes show; a run keeps them for every scan, candidates match any earlier one
        self._clouds: dict[tuple[str, int], np.ndarray] = {}
        self._positions: dict[tuple[str, int], np.ndarray] = {}
        self._images: dict[tuple[str, str, int], bytes] = {}  # (image key, space, index) -> its JPEG
        self._current: dict[str, np.ndarray] = {}  # image key -> the current scan's image (decoded once)
        self._image_keys: dict[str, str] = {}  # image key -> its entity path
        self._keypoints: dict[tuple[str, str, int], np.ndarray] = {}  # (pipeline, space, index) -> (K, 2)
        self._pipeline_image: dict[str, str] = {}  # pipeline -> its image key
        self._ranks: dict[str, int] = {}  # pipeline -> candidates logged for the last query
        self._edges: dict[tuple[str, str], _Growing] = {}  # (pipeline, kind) -> (match id, query id)
        self._fixes: dict[str, _Growing] = {}  # pipeline -> fix positions
        self._shown: set[str] = set()  # candidate parts (pair, alignment) showing a logged value
        self._batch = 0

    @classmethod
    @contextmanager
    def open(cls, target: ViewerTarget, name: str) -> Iterator[Recorder]:
        """A recorder streaming to ``target``'s viewer and / or ``.rrd`` file. Rerun's file sink writes into a
        temporary folder beside the file (the pieces its in-memory stream hands out one by one do not make one
        valid ``.rrd``: `rerun rrd verify` refuses their concatenation); when the block ends the recording is
        copied into place with `atomic_write`, and when it raises nothing is left."""
        stream = rr.RecordingStream("placerec")
        stream.send_recording_name(name)
        with ExitStack() as stack:
            sinks: list[Any] = []
            part = None
            if target.rrd is not None:
                final = Path(target.rrd).expanduser()
                folder = stack.enter_context(
                    tempfile.TemporaryDirectory(prefix=f".{final.name}.", dir=final.parent)
                )
                part = Path(folder) / final.name
                sinks.append(rr.FileSink(str(part)))
            if target.spawn:
                _spawn(stream)
                sinks.append(rr.GrpcSink())
            stream.set_sinks(*sinks)
            stack.callback(stream.disconnect)  # the file closed before its folder goes, also on an error
            rec = cls(stream, target.max_points, target.every_candidate)
            rec._layout()
            yield rec
            rec._finish()
            stream.flush()
            stream.disconnect()
            if part is not None:
                with open(part, "rb") as src, atomic_write(final) as dst:
                    shutil.copyfileobj(src, dst, 1 << 20)

    def _layout(self) -> None:
        """Static axes: the world is z up."""
        self.rr.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def _finish(self) -> None:
        """Log the growing entities (edges, fixes) whose last items are not logged yet."""
        for (label, kind), edges in self._edges.items():
            if edges.logged < len(edges.items):
                self._log_edges(label, kind)
        for label, fixes in self._fixes.items():
            if fixes.logged < len(fixes.items):
                self._log_fixes(label)

    # --- per scan -------------------------------------------------------------------------------------------

    def scan(self, index: int, scan: Scan, pose: np.ndarray | None, timestamp: float | None = None) -> None:
        """Start scan ``index`` (the timelines) and log it at ``world/scan``: its points (at most ``max_points``,
        coloured by intensity) in the sensor frame, placed at ``pose`` (T_world_sensor; None: the origin)."""
        self.index = index
        self._current.clear()
        self.rr.set_time("scan", sequence=index)
        if timestamp is not None and np.isfinite(timestamp):
            if timestamp > _EPOCH_S:
                self.rr.set_time("scan_time", timestamp=timestamp)
            else:
                self.rr.set_time("scan_time", duration=timestamp)
        keep = self.remember("scan", index, scan, pose)
        T = np.eye(4) if pose is None else np.asarray(pose, np.float64)
        points = rr.Points3D(scan.xyz[keep], colors=_colours(scan.intensity[keep]), radii=0.04)
        self.rr.log("world/scan", _transform(T), points)

    def remember(self, space: str, index: int, scan: Scan, pose: np.ndarray | None) -> np.ndarray:
        """Keep scan ``index`` of ``space`` (every other point of its subsampled cloud, its position) for the
        candidates that will match it, without logging it (a map's scans, ``space`` ``map``); returns the indices
        of the subsampled points (at most ``max_points``, fewer when over half the scan's points are not valid)."""
        # twice the points wanted, evenly spread, then the valid ones among them (testing every point of a large
        # scan costs more than the rest of logging it)
        pre = _subsample(len(scan), 2 * self.max_points)
        ok = pre[valid_points(scan.select(pre), intensity=True)]
        keep = ok[_subsample(ok.size, self.max_points)]
        self._clouds[(space, index)] = scan.xyz[keep[::2]]
        T = np.eye(4) if pose is None else np.asarray(pose, np.float64)
        self._positions[(space, index)] = T[:3, 3].copy()
        return keep

    def description(
        self,
        label: str,
        rec: PlaceRecognizer,
        scan: Scan,
        desc: Description,
        space: str = "scan",
        index: int = -1,
    ) -> None:
        """What pipeline ``label``'s front end found in the current scan: for the visual front ends the intensity
        image (``scan/image``, once per image setting) with the keypoints (``scan/image/keypoints/<label>``);
        for the 3D front ends their keypoints in the scan (``world/scan/keypoints/<label>``). For a scan of
        another ``space`` (a map's scan ``index``) the image and keypoints are only kept, for its matches."""
        from placerec.pipelines.visual import VisualFrontend

        kp = desc.get("keypoints")
        if kp is None:
            return
        kp = np.asarray(kp, np.float32)
        own = space == "scan"
        index = self.index if own else index
        if isinstance(rec, VisualFrontend) and kp.ndim == 2 and kp.shape[1] == 2:
            key = self._image(rec, scan, space, index)
            self._pipeline_image[label] = key
            self._keypoints[(label, space, index)] = kp
            if own:
                self.rr.log(f"{self._image_keys[key]}/keypoints/{_part(label)}", rr.Points2D(kp, radii=1.5))
        elif own and kp.ndim == 2 and kp.shape[1] == 3:
            self.rr.log(f"world/scan/keypoints/{_part(label)}", rr.Points3D(kp, radii=0.12))

    def _image(self, rec: Any, scan: Scan, space: str, index: int) -> str:
        """The key of ``rec``'s image setting; its image of the scan made once (and logged, for the run's own)."""
        from placerec.image import make_image

        key = rec.params.image.model_dump_json()
        if (key, space, index) not in self._images:
            last = rec.last_image  # the front end's own image of the scan it described last
            image = (
                last[1] if last is not None and last[0] is scan else make_image(scan, rec.params.image).image
            )
            jpeg = _jpeg(image)
            self._images[(key, space, index)] = jpeg
            if space == "scan":
                self._current[key] = image
            path = self._image_keys.setdefault(
                key, "scan/image" if not self._image_keys else f"scan/image_{len(self._image_keys)}"
            )
            if space == "scan":
                self.rr.log(path, _encoded(jpeg))
        return key

    # --- per query ------------------------------------------------------------------------------------------

    def candidates(
        self, label: str, cands: list[Candidate], threshold: float | None = None, edges: bool = True
    ) -> str | None:
        """Pipeline ``label``'s candidates for the current scan at ``pipelines/<label>/candidates/<rank>``: the
        verification's numbers (``verification``, text) and, for the best candidate and every accepted one (every
        candidate with ``every_candidate``), the matched image pair with the correspondences (``pair``; inliers
        green, the others red) and the match's cloud with the query's moved onto it by the candidate's pose
        (``alignment/match``, ``alignment/query``, half the points of ``world/scan`` each); what a rank showed for an earlier query and does not show for
        this one is cleared. The top candidate's numbers as scalars
        (``pipelines/<label>/top1/...``); its loop edge (`closure_kind`) added to ``world/loops/<label>/...``.
        Ranks left from a longer list of the previous query are cleared. Returns the edge's kind (not drawn
        with ``edges`` False: a caller that decides closures itself draws them with `edge`). The query is the
        candidates' ``query_id`` (a real-time SLAM detector completes earlier scans' queries late)."""
        query = cands[0].query_id if cands else self.index
        base = f"pipelines/{_part(label)}/candidates"
        for rank, c in enumerate(cands):
            path = f"{base}/{rank}"
            self.rr.log(
                f"{path}/verification", rr.TextDocument(candidate_text(c, rank), media_type="text/markdown")
            )
            shown = rank == 0 or bool(c.accepted) or self.every_candidate
            self._show(f"{path}/pair", shown and self._pair(label, path, c, query))
            self._show(f"{path}/alignment", shown and self._alignment(path, c, query))
        for rank in range(len(cands), self._ranks.get(label, 0)):
            self.rr.log(f"{base}/{rank}", rr.Clear(recursive=True))
            self._shown -= {f"{base}/{rank}/pair", f"{base}/{rank}/alignment"}
        self._ranks[label] = len(cands)
        top = cands[0] if cands else None
        if top is not None:
            v = top.verification
            self.rr.log(f"pipelines/{_part(label)}/top1/score", rr.Scalars(top.score))
            if v is not None:
                self.rr.log(f"pipelines/{_part(label)}/top1/inliers", rr.Scalars(float(v.inliers or 0)))
                self.rr.log(
                    f"pipelines/{_part(label)}/top1/fitness", rr.Scalars(float(np.nan_to_num(v.fitness)))
                )
        kind = closure_kind(top, threshold)
        if edges and kind is not None and top is not None:
            self.edge(label, kind, top.match_id, query)
        return kind

    def _show(self, path: str, logged: bool) -> None:
        """Note that ``path`` was ``logged`` for this query; clear it when it was not but is still shown."""
        if logged:
            self._shown.add(path)
        elif path in self._shown:
            self.rr.log(path, rr.Clear(recursive=True))
            self._shown.discard(path)

    def _pair(self, label: str, path: str, c: Candidate, query: int) -> bool:
        key = self._pipeline_image.get(label)
        v = c.verification
        if key is None or c.matches is None or v is None:
            return False
        ms = self.matches_in
        q_jpeg, m_jpeg = self._images.get((key, "scan", query)), self._images.get((key, ms, c.match_id))
        kq, km = self._keypoints.get((label, "scan", query)), self._keypoints.get((label, ms, c.match_id))
        if q_jpeg is None or m_jpeg is None or kq is None or km is None:
            return False
        q_img = self._current.get(key) if query == self.index else None
        q_img = _unjpeg(q_jpeg) if q_img is None else q_img
        self.rr.log(f"{path}/pair", _encoded(_jpeg(_stacked(q_img, _unjpeg(m_jpeg)))))
        m = np.asarray(c.matches, np.int64).reshape(-1, 2)
        a, b = kq[m[:, 0]], km[m[:, 1]] + np.array([0, q_img.shape[0]], np.float32)
        inlier = np.zeros(len(m), bool) if v.inlier_mask is None else np.asarray(v.inlier_mask, bool)
        strips = np.stack([a, b], axis=1)
        colours = np.where(inlier[:, None], ACCEPTED, REJECTED).astype(np.uint8)
        self.rr.log(f"{path}/pair/correspondences", rr.LineStrips2D(strips, colors=colours, radii=0.5))
        return True

    def _alignment(self, path: str, c: Candidate, query: int) -> bool:
        cloud, match = self._clouds.get(("scan", query)), self._clouds.get((self.matches_in, c.match_id))
        if c.relative_pose is None or cloud is None or match is None:
            return False
        T = np.asarray(c.relative_pose, np.float64)
        self.rr.log(f"{path}/alignment/match", rr.Points3D(match, colors=MATCH_CLOUD, radii=0.04))
        self.rr.log(f"{path}/alignment/query", rr.Points3D(_moved(cloud, T), colors=QUERY_CLOUD, radii=0.04))
        return True

    def edge(self, label: str, kind: str, match_id: int, query_id: int) -> None:
        """Add a loop edge ``match_id`` -- ``query_id`` of ``kind`` (``accepted``, ``rejected``) to
        ``world/loops/<label>/<kind>``, drawn between the places the two scans were logged at (logged again as it
        grows, `_Growing`)."""
        if self._edges.setdefault((label, kind), _Growing()).add((match_id, query_id)):
            self._log_edges(label, kind)

    def _log_edges(self, label: str, kind: str) -> None:
        edges = self._edges[(label, kind)]
        edges.logged = len(edges.items)
        ends = [
            (self._positions.get((self.matches_in, m)), self._positions.get(("scan", q)))
            for m, q in edges.items
        ]
        strips = [np.stack([a, b]) for a, b in ends if a is not None and b is not None]
        colour = REJECTED if kind == "rejected" else ACCEPTED if kind == "accepted" else INJECTED
        self.rr.log(f"world/loops/{_part(label)}/{kind}", rr.LineStrips3D(strips, colors=colour, radii=0.08))

    def replace_positions(self, poses: np.ndarray) -> None:
        """Move the loop edges onto new scan positions (e.g. SLAM's optimised poses) and draw them again."""
        for i, p in enumerate(poses):
            self._positions[("scan", i)] = np.asarray(p[:3, 3], np.float64)
        for label, kind in list(self._edges):
            self._log_edges(label, kind)

    # --- trajectories, posteriors, fixes ------------------------------------------------------------------------

    def trajectory(self, name: str, poses: np.ndarray, static: bool = False) -> None:
        """The positions of ``poses`` (N, 4, 4) as one line at ``world/trajectory/<name>`` (``static``: for the
        whole recording, e.g. the ground truth)."""
        xyz = np.asarray(poses, np.float64).reshape(-1, 4, 4)[:, :3, 3]
        self.rr.log(f"world/trajectory/{name}", rr.LineStrips3D([xyz], radii=0.06), static=static)

    def points(self, path: str, xyz: np.ndarray, colour: tuple[int, int, int], static: bool = False) -> None:
        """Plain points at ``path`` (e.g. a map's keyframe positions, ``world/map/keyframes``)."""
        self.rr.log(path, rr.Points3D(np.asarray(xyz, np.float32), colors=colour, radii=0.15), static=static)

    def posterior_observer(self, label: str) -> Callable[[PosteriorStep], None]:
        """The callback `placerec.pipelines.probabilistic_voting.ProbabilisticVoting.posterior_observer` takes:
        each batch's posterior over places at ``pipelines/<label>/posterior`` (a bar per place, in entry order)
        and its largest value at ``pipelines/<label>/posterior_max``, on the ``ishot_batch`` timeline."""

        def observe(step: PosteriorStep) -> None:
            self._batch += 1
            self.rr.set_time("ishot_batch", sequence=self._batch)
            prob = np.asarray(step.probabilities, np.float64)
            self.rr.log(f"pipelines/{_part(label)}/posterior", rr.BarChart(prob))
            self.rr.log(f"pipelines/{_part(label)}/posterior_max", rr.Scalars(float(prob.max(initial=0.0))))

        return observe

    def localized(self, label: str, cands: list[Candidate], threshold: float | None = None) -> None:
        """A localisation query's candidates (`candidates`, their edges drawn to the map scans they matched) and
        its fix (`fix`): the best candidate's ``T_world_query`` when its edge is ``accepted``."""
        kind = self.candidates(label, cands, threshold)
        top = cands[0] if cands else None
        ok = kind == "accepted" and top is not None and top.T_world_query is not None
        text = "no candidate" if top is None else candidate_text(top, 0)
        self.fix(label, None if top is None else top.T_world_query, text, ok)

    def fix(self, label: str, T_world_query: np.ndarray | None, text: str, accepted: bool) -> None:
        """A relocalisation's answer for the current scan: ``world/fix/<label>`` (the scan's pose in the map and
        its cloud there when accepted, cleared otherwise), the answer in words at ``localize/<label>``, and the
        accepted fixes so far as points at ``world/fixes/<label>`` (logged again as they grow, `_Growing`)."""
        self.rr.log(f"localize/{_part(label)}", rr.TextDocument(text, media_type="text/markdown"))
        if not accepted or T_world_query is None:
            self.rr.log(f"world/fix/{_part(label)}", rr.Clear(recursive=True))
            return
        T = np.asarray(T_world_query, np.float64)
        cloud = self._clouds.get(("scan", self.index), np.zeros((0, 3), np.float32))
        self.rr.log(f"world/fix/{_part(label)}", rr.Points3D(_moved(cloud, T), colors=ACCEPTED, radii=0.05))
        if self._fixes.setdefault(label, _Growing()).add(T[:3, 3].copy()):
            self._log_fixes(label)

    def _log_fixes(self, label: str) -> None:
        fixes = self._fixes[label]
        fixes.logged = len(fixes.items)
        self.rr.log(
            f"world/fixes/{_part(label)}", rr.Points3D(np.array(fixes.items), colors=ACCEPTED, radii=0.25)
        )

    @contextmanager
    def watching(self, label: str, rec: PlaceRecognizer) -> Iterator[None]:
        """Inside the block, an ``ishot-prob`` recognizer's posterior is logged batch by batch
        (`posterior_observer`); other recognizers have nothing to watch."""
        from placerec.pipelines.probabilistic_voting import ProbabilisticVoting

        if not isinstance(rec, ProbabilisticVoting):
            yield
            return
        rec.posterior_observer = self.posterior_observer(label)
        try:
            yield
        finally:
            rec.posterior_observer = None
