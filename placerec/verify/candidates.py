"""The candidate-verification step every pipeline shares (issue #12 item 5).

::

    from placerec.verify.candidates import CloudStore, Retrieved, VerifiedParams, scan_cloud, verify_candidates

    description["cloud"] = scan_cloud(scan, params.verify)       # in describe(): cached with the rest
    store.add(scan_id, description["cloud"])                            # in add_description(): the database's
    retrieved = [Retrieved(match_id, retrieval_score, src_kp, dst_kp)]  # or init=T_guess for ICP only
    cands = verify_candidates(description["cloud"], retrieved, store, params.verify, query_id, k)

* `VerifiedParams` is the ``verify`` section of a pipeline's Params: ``enabled``, ``top_k`` and, in the same
  section, the `placerec.verify.VerifyParams` of the stage.
* `scan_cloud` voxelises a scan at the ICP target voxel (``icp.voxel_size``), float32: what a description keeps
  so the description cache holds it; the query is prepared from it once per query (`as_source`, at the coarser
  source voxel), each database cloud once (`CloudStore.target`, kept for later queries).
* `verify_candidates` verifies the first ``top_k`` retrieved candidates (in the order given: best retrieval
  first) with `placerec.verify.verify` (keypoint correspondences) or `verify_icp` (an initial guess ``init``),
  and returns `placerec.types.Candidate`\\ s with ``relative_pose = T_match_query`` (the ICP pose), ``score`` = the
  verified score, ``inliers`` (RANSAC inliers; None for ICP only), ``verification`` (the `Verification`),
  ``retrieval_score``, ``accepted`` and ``verify_ms`` (the candidate's verification time plus its share of
  preparing the clouds, plus the `Retrieved`'s ``verify_ms`` for finding the correspondences, plus an equal share
  of the time of the verified candidates beyond ``k``, so the returned ones add up to the whole stage: the runner's 'verify' stage,
  `placerec.loop_closure.split_verify_time`), sorted by verified score (ties: retrieval score), at most ``k``.

With ``between`` (a callable), `verify_candidates` verifies the candidates on their own matches first and asks it
for the answer before any second chance (`Retrieved.guided`) is tried, reusing those verifications after it: a
pipeline puts `verify_near` there, the second chance of a query with a motion prior whose candidates gave no
answer (``verify.guided.near_metres``): the places the prior predicts near the query, registered by ICP alone
from the prediction (`placerec.verify.guided`).

Rejected candidates are **kept**, ranked below the accepted ones of equal score, so PR curves stay continuous:
with ``acceptance = "score"`` a candidate rejected for its score keeps its verified score (below ``min_score`` by
definition); one that the ``eps_icp`` rule (``"eps_icp"``, ``"both"``) or a gate (``min_fitness``,
``min_fitness_ratio``, ``min_constraint``) rejects scores 0 (its overlap score does not carry that rule), and so
do those rejected before ICP. A threshold of ``min_score`` or more on ``Candidate.score`` thus never accepts a
rejected candidate, and an accepted candidate always ranks above a rejected one. Retrieved
candidates beyond ``top_k`` are dropped: their retrieval scores are on another scale than verified scores.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, Literal

import numpy as np
from pydantic import Field

from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.quantise import FixedPointCloud, PackedCloud
from placerec.types import Candidate, MotionPrior, take_rows
from placerec.verify.guided import GuidedParams, answer_pose, within
from placerec.verify.icp import IcpCloud, as_points
from placerec.verify.params import VerifyParams
from placerec.verify.spill import SpilledArrays, SpillFile, SpillRef, memory_mapped
from placerec.verify.verify import Hypothesis, Verification, as_source, as_target, complete, hypothesise
from placerec.verify.voxel_grid import voxel_points

__all__ = [
    "VerifiedParams",
    "Retrieved",
    "CloudStore",
    "scan_cloud",
    "verify_candidates",
    "verify_near",
    "feature_arrays",
]


class VerifiedParams(VerifyParams):
    """The ``verify`` section of a pipeline: whether and how many retrieved candidates are verified, and the
    verification stage's own settings (`VerifyParams`: RANSAC, consistency grouping, ICP, acceptance)."""

    enabled: bool = Field(
        True, description="verify the retrieved candidates geometrically (RANSAC / ICP, placerec.verify)"
    )
    top_k: int = Field(
        3,
        ge=1,
        le=1000,
        description="retrieved candidates verified per query (best retrieval first); the rest dropped",
    )
    icp_top_k: int | None = Field(
        None,
        ge=1,
        le=1000,
        description="of the candidates that pass RANSAC, ICP refines (and may accept) only this many, those with the"
        " most inliers; the rest are rejected at 'rank' (None: all)",
    )
    guided: GuidedParams = Field(
        default_factory=GuidedParams,
        description="a second chance for candidates RANSAC finds no pose for: matching within the caller's motion "
        "prior (placerec.verify.guided)",
    )
    cloud_store: Literal["float32", "int16", "int16-zlib"] = Field(
        "int16-zlib",
        description="how the database keeps each added entry's ICP cloud in memory: int16-zlib, the int16 codes "
        "compressed losslessly (placerec.quantise.PackedCloud: ~0.65 of int16's bytes, ~0.6 ms to unpack when a "
        "cloud is first prepared for ICP); int16 fixed point around the cloud's centre (6 bytes a point; error at "
        "most half a step: 0.6 mm within 40 m, 1.8 mm within 120 m; verified F1 unchanged, docs/benchmarks.md); "
        "or float32 (12 bytes)",
    )
    cloud_budget_mb: float | None = Field(
        128.0,
        gt=0,
        le=1e6,
        description="RAM (MB) for what each database entry keeps for verification: half for the stored ICP clouds "
        "(beyond it the oldest move to a temporary file, cloud_spill_dir, read back when a candidate reaches ICP), a "
        "quarter for the ICP targets prepared for reuse, a quarter for the 2D pipelines' keypoints, their 3D points "
        "and descriptors (spilled likewise); None: everything in RAM. Results do not depend on it. A run-time "
        "setting: not recorded in a saved database",
        json_schema_extra={"runtime": True},
    )
    cloud_spill_dir: str | None = Field(
        None,
        description="folder of the file what is over cloud_budget_mb moves to (None: the system's temporary "
        "folder); the file has no name there and is gone when the process ends",
        json_schema_extra={"runtime": True},
    )


@dataclass
class Retrieved:
    """One retrieved candidate to verify: ``src_kp`` (query frame) corresponds row by row to ``dst_kp`` (match
    frame), ``quality`` orders them for the consistency grouping (lower is better, e.g. descriptor distance);
    without keypoints, ICP starts from ``init`` (``T_match_query``; None: identity). ``target`` (no arguments,
    returns the prepared `IcpCloud`) replaces the store's cloud of ``match_id`` as ICP target, e.g. a place merged
    with its neighbours. ``extra`` is copied into the candidate; ``verify_ms`` is the time the pipeline took to find
    the correspondences, counted in the candidate's ``verify_ms``. ``pairs`` (M, 2): the (query feature, match
    feature) indices of the correspondences, row by row (the candidate's ``matches``; None: not known).
    ``guided`` (no arguments) gives this candidate again with the correspondences a motion prior allows
    (`placerec.verify.guided`; None: no prior), tried when RANSAC finds no pose on these (``verify.guided``).
    ``hypothesis``: its `hypothesise` with the parameters `verify_candidates` is given, when the pipeline made it
    already (on the thread that matched it: `placerec.pipelines.visual.VisualFrontend._retrieved_all`), its time
    then in ``verify_ms``; None: `verify_candidates` makes it."""

    match_id: int
    retrieval_score: float
    src_kp: np.ndarray | None = None
    dst_kp: np.ndarray | None = None
    quality: np.ndarray | None = None
    init: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    target: Callable[[], IcpCloud] | None = None
    verify_ms: float = 0.0
    pairs: np.ndarray | None = None
    guided: Callable[[], Retrieved] | None = None
    hypothesis: Hypothesis | None = None


def scan_cloud(scan: Any, params: VerifyParams | None = None) -> np.ndarray:
    """The scan's valid points (a `Scan` or (N, 3+) array) cropped to ``icp.max_range`` and voxelised at
    ``icp.voxel_size``: (M, 3) float32, to keep in a description."""
    icp = (params or VerifyParams()).icp
    p = as_points(scan, "scan")
    if icp.max_range is not None:
        p = take_rows(p, np.einsum("ni,ni->n", p, p) <= icp.max_range**2)
    return voxel_points(p, icp.voxel_size)


class CloudStore:
    """Each database entry's cloud (from `scan_cloud`), prepared as an ICP target on first use.

    * Stored clouds are kept as ``dtype`` says (``VerifiedParams.cloud_store``): ``"float32"``, ``"int16"``
      (`placerec.quantise.FixedPointCloud`: half the bytes; decoded when prepared) or ``"int16-zlib"``
      (`placerec.quantise.PackedCloud`: the same codes compressed losslessly, about a third of the bytes).
      Memory-mapped clouds (a database loaded with ``mmap``) and those read by `from_arrays` stay as they are (a
      mapped file's pages take no RAM until used). `add_deferred` stores a function making the cloud instead,
      called when the cloud is first needed (e.g. from a memory-mapped places database).
    * ``budget_mb`` (``VerifiedParams.cloud_budget_mb``; None: no limit) bounds the RAM of both: once the stored
      clouds pass `CLOUDS_SHARE` of it, the oldest move, in the same form, to an unnamed temporary file in
      ``spill_dir`` (`placerec.verify.spill.SpillFile`, `spill_file`) and are read back when prepared (`nbytes`,
      `spilled`); the prepared targets, counted at their arrays' bytes (`prepared_bytes`), are kept within
      `PREPARED_SHARE` of it and within ``max_prepared`` of them, least recently used dropped (one takes ~1-3 MB
      for an OS1-64 scan at 0.4 m and 30-90 ms to prepare). The rest, `FEATURES_SHARE`, is for a pipeline's own
      per-entry arrays (`feature_arrays`). Either way a cloud reads back bit for bit: results do not depend on the
      budget.
    * ``arrays`` / `from_arrays` give the clouds for a pipeline's saved database (float32 points either way).
    """

    def __init__(
        self,
        params: VerifyParams | None = None,
        max_prepared: int = 128,
        dtype: str = "float32",
        budget_mb: float | None = None,
        spill_dir: str | None = None,
    ) -> None:
        if dtype not in _ENCODERS:
            raise ConfigError(f"cloud store {dtype!r} is unknown; allowed: {sorted(_ENCODERS)}")
        if budget_mb is not None and not (np.isfinite(budget_mb) and budget_mb > 0):
            raise ConfigError(
                f"verify.cloud_budget_mb must be a positive number of MB or None, got {budget_mb}"
            )
        self.params = params or VerifyParams()
        self.max_prepared = max_prepared
        self.dtype = dtype
        self.budget_bytes = None if budget_mb is None else int(budget_mb * 1e6)
        self._clouds: dict[int, _Stored] = {}
        self._prepared: OrderedDict[int, IcpCloud] = OrderedDict()
        self._ram = 0  # bytes of the stored clouds held in RAM (`_ram_bytes` of each)
        self._prepared_ram = 0
        self._spill = SpillFile(spill_dir)
        self._in_ram: OrderedDict[int, None] = (
            OrderedDict()
        )  # ids whose cloud may move to the file, oldest first

    @property
    def spill_file(self) -> SpillFile:
        """The file this store's clouds over the budget go to (shared with `feature_arrays`)."""
        return self._spill

    @classmethod
    def for_pipeline(cls, verify: VerifiedParams) -> CloudStore:
        """The store of a pipeline's ``verify`` section: its ``cloud_store``, budget and spill folder."""
        return cls(
            verify,
            dtype=verify.cloud_store,
            budget_mb=verify.cloud_budget_mb,
            spill_dir=verify.cloud_spill_dir,
        )

    def __len__(self) -> int:
        return len(self._clouds)

    def __contains__(self, scan_id: object) -> bool:
        return scan_id in self._clouds

    def _put(self, scan_id: int, value: _Stored) -> None:
        self._drop(scan_id)
        self._clouds[scan_id] = value
        size = _ram_bytes(value)
        if size:
            self._ram += size
            self._in_ram[scan_id] = None
            self._spill_over_budget()

    def _drop(self, scan_id: int) -> None:
        old = self._clouds.pop(scan_id, None)
        if old is not None and scan_id in self._in_ram:
            del self._in_ram[scan_id]
            self._ram -= _ram_bytes(old)
        tgt = self._prepared.pop(scan_id, None)
        if tgt is not None:
            self._prepared_ram -= _target_bytes(tgt)

    def _spill_over_budget(self) -> None:
        if self.budget_bytes is None:
            return
        while self._ram > self.budget_bytes * CLOUDS_SHARE and self._in_ram:
            sid, _ = self._in_ram.popitem(last=False)
            value = self._clouds[sid]
            self._ram -= _ram_bytes(value)
            self._clouds[sid] = _spilled(value, self._spill)

    def add(self, scan_id: int, cloud: np.ndarray) -> None:
        mapped = memory_mapped(cloud)  # a memory-mapped file's pages cost no RAM: kept as they are
        c = np.asarray(cloud, dtype=np.float32)
        if c.ndim != 2 or c.shape[1] != 3:
            raise ScanDataError(f"cloud of entry {scan_id} must have shape (M, 3), got {c.shape}")
        self._put(int(scan_id), c if mapped else _ENCODERS[self.dtype](c))

    def add_deferred(self, scan_id: int, make: Callable[[], np.ndarray]) -> None:
        """Store ``make`` (no arguments, returns the (M, 3) cloud) for entry ``scan_id``: called on each use."""
        self._put(int(scan_id), make)

    def cloud(self, scan_id: int) -> np.ndarray:
        """Entry ``scan_id``'s cloud, (M, 3) float32 (decoded when kept as int16, read back when spilled, made
        when deferred)."""
        try:
            c = self._clouds[int(scan_id)]
        except KeyError:
            raise ScanDataError(f"no cloud stored for entry {scan_id}") from None
        if isinstance(c, _Spill):
            c = c.restore(self._spill)
        if isinstance(c, FixedPointCloud | PackedCloud):
            return c.decode()
        return np.asarray(c(), np.float32) if callable(c) else c

    @property
    def nbytes(self) -> int:
        """Bytes of the stored clouds held in RAM (not the prepared targets, nor spilled, deferred or
        memory-mapped clouds)."""
        return self._ram

    @property
    def spilled(self) -> tuple[int, int]:
        """(clouds, bytes) moved to the spill file."""
        n = sum(isinstance(c, _Spill) for c in self._clouds.values())
        return n, self._spill.nbytes

    @property
    def prepared_bytes(self) -> int:
        """Bytes of the prepared ICP targets kept for reuse (their arrays: points, normals, covariances)."""
        return self._prepared_ram

    def target(self, scan_id: int) -> IcpCloud:
        """Entry ``scan_id``'s cloud prepared for ICP (`as_target`), cached."""
        sid = int(scan_id)
        if sid in self._prepared:
            self._prepared.move_to_end(sid)
            return self._prepared[sid]
        tgt = as_target(self.cloud(sid), self.params)
        self._prepared[sid] = tgt
        self._prepared_ram += _target_bytes(tgt)
        cap = None if self.budget_bytes is None else self.budget_bytes * PREPARED_SHARE
        while len(self._prepared) > 1 and (
            len(self._prepared) > self.max_prepared or (cap is not None and self._prepared_ram > cap)
        ):
            _, old = self._prepared.popitem(last=False)
            self._prepared_ram -= _target_bytes(old)
        return tgt

    def arrays(self, ids: Iterable[int]) -> dict[str, np.ndarray]:
        """``cloud_counts`` and ``cloud_xyz`` of the entries ``ids`` (in that order), for saving: decoded one at a
        time into the output, so the only float32 copy of the clouds is ``cloud_xyz`` itself."""
        ids = [int(i) for i in ids]
        counts = np.asarray([self._count(i) for i in ids], np.int64)
        ends = np.cumsum(counts)
        xyz = np.empty((int(ends[-1]) if ids else 0, 3), np.float32)
        for i, end, n in zip(ids, ends, counts, strict=True):
            xyz[end - n : end] = self.cloud(i)
        return {"cloud_counts": counts, "cloud_xyz": xyz}

    def _count(self, scan_id: int) -> int:
        c = self._clouds.get(scan_id)
        return len(self.cloud(scan_id)) if c is None or callable(c) else len(c)

    def from_arrays(self, ids: Sequence[int], arrays: Mapping[str, np.ndarray], path: Any = "") -> None:
        """Replace the clouds by those of `arrays` (saved for ``ids``); `ArtifactError` when they disagree."""
        missing = [k for k in ("cloud_counts", "cloud_xyz") if k not in arrays]
        if missing:
            raise ArtifactError(
                f"{path}: the database has no {' / '.join(missing)} (the clouds verification needs)"
            )
        counts, xyz = np.asarray(arrays["cloud_counts"]), np.asarray(arrays["cloud_xyz"], np.float32)
        if counts.shape != (len(ids),) or (counts < 0).any() or int(counts.sum()) != xyz.shape[0]:
            raise ArtifactError(f"{path}: cloud_counts do not match the entries and cloud_xyz")
        for sid in list(self._clouds):
            self._drop(sid)
        self._spill.close()
        # kept as read, int16 or not: views of the file's pages when the database was loaded memory-mapped
        for i, c in zip(ids, np.split(xyz, np.cumsum(counts)[:-1]) if len(ids) else [], strict=True):
            self._clouds[int(i)] = c  # views of one array: neither counted in the budget nor spilled


#: the shares of ``verify.cloud_budget_mb``: the stored clouds, the prepared ICP targets, and the per-entry arrays a
#: pipeline keeps for its matching (the 2D pipelines' keypoints, their 3D points and descriptors: `feature_arrays`)
CLOUDS_SHARE, PREPARED_SHARE, FEATURES_SHARE = 0.5, 0.25, 0.25


def feature_arrays(store: CloudStore, n: int) -> list[SpilledArrays]:
    """``n`` mappings id -> array for a pipeline's per-entry arrays, sharing `FEATURES_SHARE` of ``store``'s budget
    equally and its spill file (`placerec.verify.spill.SpilledArrays`)."""
    b = store.budget_bytes
    share = None if b is None else int(b * FEATURES_SHARE / n)
    return [SpilledArrays(share, store.spill_file) for _ in range(n)]


#: how `CloudStore.add` keeps a cloud per ``dtype`` (``VerifiedParams.cloud_store``)
_ENCODERS: dict[str, Callable[[np.ndarray], np.ndarray | FixedPointCloud | PackedCloud]] = {
    "float32": lambda c: c,
    "int16": FixedPointCloud.encode,
    "int16-zlib": partial(PackedCloud.encode, level=2),
}


@dataclass(frozen=True)
class _Spill:
    """A stored cloud moved to the spill file: its bytes at ``ref``, and what rebuilds it in its ``form``."""

    form: str  # "float32", "int16" or "int16-zlib"
    ref: SpillRef
    n: int
    centre: np.ndarray | None = None
    scale: float = 1.0

    def __len__(self) -> int:
        return self.n

    def restore(self, spill: SpillFile) -> np.ndarray | FixedPointCloud | PackedCloud:
        data = spill.read(self.ref)
        if self.form == "int16-zlib":
            return PackedCloud(data, self.n, self.centre, self.scale)  # type: ignore[arg-type]
        if self.form == "int16":
            codes = np.frombuffer(data, np.int16).reshape(self.n, 3).copy()
            return FixedPointCloud(codes, self.centre, self.scale)  # type: ignore[arg-type]
        return np.frombuffer(data, np.float32).reshape(self.n, 3).copy()


#: what `CloudStore` keeps per entry: a cloud (float32, int16 codes or packed), one moved to the spill file, or
#: a function making it
_Stored = np.ndarray | FixedPointCloud | PackedCloud | _Spill | Callable[[], np.ndarray]


def _spilled(value: _Stored, spill: SpillFile) -> _Spill:
    """``value`` (a cloud in RAM) written to ``spill``."""
    if isinstance(value, PackedCloud):
        return _Spill("int16-zlib", spill.write(value.data), value.n, value.centre, value.scale)
    if isinstance(value, FixedPointCloud):
        codes = np.ascontiguousarray(value.codes, np.int16)
        return _Spill("int16", spill.write(codes.tobytes()), len(codes), value.centre, value.scale)
    c = np.ascontiguousarray(value, np.float32)
    return _Spill("float32", spill.write(c.tobytes()), len(c))


def _ram_bytes(value: _Stored) -> int:
    """RAM a stored value holds that the budget counts: 0 for spilled, deferred and memory-mapped clouds."""
    if isinstance(value, _Spill) or callable(value) or memory_mapped(value):
        return 0
    return int(value.nbytes)


def _target_bytes(t: IcpCloud) -> int:
    """The bytes a prepared target holds: its float64 points, and the backend's cloud (points, normals and
    covariances as 4-vectors / 4x4 float64) and search tree, ~`_NATIVE_BYTES_PER_POINT` a point."""
    return int(t.points.nbytes) + len(t) * _NATIVE_BYTES_PER_POINT


#: small_gicp's target per point: points and normals (2 x 32 bytes), covariances (128), KD-tree (~16)
_NATIVE_BYTES_PER_POINT = 208


def _score(v: Verification, params: VerifyParams) -> float:
    """The candidate's score: the verified score when accepted, or when rejected for that score alone (below
    ``min_score``); 0 when another rule or gate rejected it (module docstring)."""
    if v.accepted or (params.score.acceptance == "score" and v.rejection == "score"):
        return float(v.score)
    return 0.0


#: what `verify_candidates` asks between the candidates' own matches and their second chances: given those
#: candidates (verified, best first, at most ``k``) and the query's cloud as prepared so far, the answer to return
#: instead, or None to go on to the second chances
Between = Callable[[list[Candidate], np.ndarray | IcpCloud], list[Candidate] | None]


def verify_candidates(
    query_cloud: np.ndarray | IcpCloud,
    retrieved: Sequence[Retrieved],
    store: CloudStore,
    params: VerifiedParams,
    query_id: int = -1,
    k: int | None = None,
    between: Between | None = None,
) -> list[Candidate]:
    """Verify the first ``params.top_k`` of ``retrieved`` against ``store``'s clouds (see the module docstring);
    returns at most ``k`` (None: all verified) candidates, best verified first.

    A candidate that grouping or RANSAC rejects on its own matches gets its second chance (``Retrieved.guided``,
    with ``verify.guided.enabled``) after every candidate was hypothesised on its own. With ``between``, the
    candidates on their own matches are verified first and handed to it; what it returns is the answer, and only
    when it returns None do the second chances follow, reusing the verifications already made (the time
    ``between`` took is shared by the candidates)."""
    todo = list(retrieved)[: params.top_k]
    if not todo:
        return []
    vp = params
    hyps, ms = [], []
    for r in todo:
        t0 = time.perf_counter()
        h = r.hypothesis
        hyps.append(h if h is not None else hypothesise(r.src_kp, r.dst_kp, r.init, vp, r.quality))
        ms.append((time.perf_counter() - t0) * 1e3 + r.verify_ms)
    done: dict[int, Verification] = {}
    guided: set[int] = set()
    source: Any = query_cloud

    def answer() -> list[Candidate]:
        nonlocal source
        refined = _to_refine(hyps, params.icp_top_k, guided)
        new = sorted(j for j in refined if j not in done)
        if new:
            t0 = time.perf_counter()
            source = as_source(source, vp)
            shared = (time.perf_counter() - t0) * 1e3 / len(new)
        for j in new:  # the match is prepared (and cached) only here
            t1 = time.perf_counter()
            v = complete(source, todo[j].target or partial(store.target, todo[j].match_id), hyps[j], vp)
            if j in guided and v.accepted and v.score < vp.guided.min_score:
                v = replace(v, accepted=False, rejection="guided_score")
            done[j] = v
            ms[j] += (time.perf_counter() - t1) * 1e3 + shared
        return _ranked(todo, hyps, done, refined, ms, vp, query_id, k)

    if between is not None:
        first = answer()
        t0 = time.perf_counter()
        instead = between(first, source)
        if instead is not None:
            return instead
        spent = (time.perf_counter() - t0) * 1e3 / len(todo)
        for j in range(len(ms)):
            ms[j] += spent
    if vp.guided.enabled:
        for j, (r, h) in enumerate(zip(todo, hyps, strict=True)):
            if h.rejected_at in ("grouping", "ransac") and r.guided is not None:
                t0 = time.perf_counter()
                again = r.guided()
                second = hypothesise(again.src_kp, again.dst_kp, None, vp, again.quality)
                ms[j] += (time.perf_counter() - t0) * 1e3
                if second.rejected_at is None:
                    todo[j], hyps[j] = again, second
                    guided.add(j)
                    ms[j] += again.verify_ms - r.verify_ms
    return answer()


def _ranked(
    todo: Sequence[Retrieved],
    hyps: Sequence[Hypothesis],
    done: Mapping[int, Verification],
    refined: set[int],
    ms: Sequence[float],
    vp: VerifiedParams,
    query_id: int,
    k: int | None,
) -> list[Candidate]:
    """`verify_candidates`' answer: each candidate's verification (``done`` for the ``refined``, its rejection
    before ICP else), sorted by verified score, at most ``k``."""
    out: list[Candidate] = []
    for j, (r, h) in enumerate(zip(todo, hyps, strict=True)):
        v = done[j] if j in refined else h.rejected(None if h.rejected_at else "rank")
        out.append(
            Candidate(
                query_id,
                int(r.match_id),
                _score(v, vp),
                v.T_match_query,
                v.inliers,
                dict(r.extra),
                accepted=bool(v.accepted),
                verification=v,
                retrieval_score=float(r.retrieval_score),
                verify_ms=ms[j],
                matches=None if r.pairs is None else np.asarray(r.pairs, np.int32).reshape(-1, 2),
            )
        )
    # retrieval_score is set on every candidate above (`or 0.0` only narrows its Optional type)
    out.sort(key=lambda c: (-c.score, not c.accepted, -(c.retrieval_score or 0.0)))
    kept = out[: k if k is not None else len(out)]
    # the candidates not returned were verified too: their time is shared by those returned
    dropped_ms = sum(c.verify_ms for c in out[len(kept) :])
    return [replace(c, verify_ms=c.verify_ms + dropped_ms / len(kept)) for c in kept]


def verify_near(
    query_cloud: np.ndarray | IcpCloud,
    prior: MotionPrior,
    store: CloudStore,
    params: VerifiedParams,
    eligible: Callable[[int], bool],
    query_id: int = -1,
) -> Candidate | None:
    """The first place ``prior`` predicts within ``guided.near_metres`` of the query that ICP alone, started from
    the prediction, registers with a score of at least ``guided.min_score`` and a pose within the prediction's
    bounds, trying at most ``guided.near_candidates`` of the ``eligible`` entries, nearest first (module
    docstring); None when none does or ``near_metres`` is unset. The time of the tries that failed is counted in
    the one returned (marked ``near`` in its ``extra``)."""
    g = params.guided
    if g.near_metres is None:
        return None
    reach = g.max_metres if g.max_metres is not None else float("inf")
    spent = 0.0
    tried = 0
    for match_id, prediction in prior.near(g.near_metres, reach):
        if tried == g.near_candidates:
            break
        if not eligible(match_id):
            continue
        tried += 1
        t0 = time.perf_counter()
        query_cloud = as_source(query_cloud, params)  # prepared once for every try
        r = Retrieved(match_id, 0.0, init=prediction.T_match_query, extra={"near": 1})
        (c,) = verify_candidates(query_cloud, [r], store, params, query_id, 1)
        spent += (time.perf_counter() - t0) * 1e3
        pose = answer_pose(c, g)
        if pose is not None and within(prediction, pose):
            return replace(c, verify_ms=spent)
    return None


def _to_refine(hyps: Sequence[Hypothesis], icp_top_k: int | None, guided: set[int] | None = None) -> set[int]:
    """Indices of the hypotheses ICP refines: those not rejected, at most ``icp_top_k`` of them with the most
    RANSAC inliers (ties, and ICP-only hypotheses: retrieval order), those posed from their own matches before the
    ``guided`` ones (a prior's second chance takes only the ICP left over)."""
    alive = [j for j, h in enumerate(hyps) if h.rejected_at is None]
    if icp_top_k is not None:
        second = guided or set()
        alive = sorted(alive, key=lambda j: (j in second, -(hyps[j].inliers or 0)))[:icp_top_k]
    return set(alive)
