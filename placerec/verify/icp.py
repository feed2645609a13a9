"""ICP refinement between two voxelised scans, through a well-kept library (small_gicp or Open3D).

A scan is prepared once per role (`prepare_target` for the matched scan: voxel grid ``voxel_size``, normals /
covariances, search tree; `prepare_source` for the query: the coarser ``source_voxel_size``, which sets the cost
per candidate), so a pipeline that verifies k candidates prepares the query once and each database scan once.
`refine` runs point-to-plane ICP (ISHOT paper Sec. IV-F; or small_gicp's GICP) from an initial ``T_target_source``
and measures the result the same way for every backend (`alignment_stats`): the nearest target voxel of each
transformed source voxel (``stats_points`` of them, evenly strided) gives the overlap ``fitness`` (the share
within ``fitness_distance``), the ``rmse`` of those distances, and the ISHOT paper's ICP residual (the mean
squared nearest-neighbour distance, PCL's ``getFitnessScore``) for the eps_ICP rule. ``docs/verification.md``
compares the backends.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit

from placerec.errors import DependencyError, ScanDataError
from placerec.threads import available_threads, import_openmp
from placerec.types import take_rows
from placerec.verify.params import IcpParams

__all__ = [
    "IcpCloud",
    "IcpResult",
    "coarser_source",
    "finer_source",
    "prepare_source",
    "prepare_target",
    "prepare_threads",
    "refine",
    "alignment_stats",
    "as_points",
]


@dataclass(frozen=True)
class IcpCloud:
    """A voxelised scan ready for ICP: ``points`` (M, 3) float64, the backend's own cloud (and tree), the role
    (``source`` or ``target``), the parameters it was made with and, for a target, a small_gicp KD-tree over
    ``points`` for the statistics (the backend's own one for small_gicp; 2.5x faster than SciPy's here)."""

    points: np.ndarray
    role: str
    backend: str
    voxel_size: float
    native: Any
    native_tree: Any = None
    tree: Any = None
    prepare_ms: float = 0.0
    #: clouds made from this one, by voxel size (`coarser_source`, `finer_source`): a query's other grids are made
    #: once however many candidates it is verified against
    derived: dict[float, IcpCloud] = field(default_factory=dict, compare=False, repr=False)
    #: a source's points before its voxel grid (`finer_source` voxelises them again); None for a target
    origin: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True)
class IcpResult:
    """``T`` = T_target_source after ICP; overlap ``fitness`` in [0, 1], ``rmse`` (m) of the overlapping voxels,
    ``residual`` (m^2, the eps_ICP quantity), iterations reported by the backend (-1 when it does not say),
    ``constraint`` (`alignment_stats`; NaN when not measured)."""

    T: np.ndarray
    fitness: float
    rmse: float
    residual: float
    iterations: int
    ms: float
    constraint: float = math.nan


def as_points(points: Any, what: str = "points") -> np.ndarray:
    """(N, 3) float64 finite points from an array (extra columns such as intensity are dropped) or a `Scan`."""
    xyz = np.asarray(getattr(points, "xyz", points))
    if xyz.dtype not in (np.float32, np.float64):  # the types the kernel takes (no float16 / longdouble)
        xyz = xyz.astype(np.float64)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise ScanDataError(f"{what} must be an (N, 3) array, got shape {xyz.shape}")
    # selected in the input's own float type (finiteness and zeros do not change in float64), then only the
    # kept points converted
    p = xyz[:, :3]
    return np.ascontiguousarray(take_rows(p, _returns(p)), dtype=np.float64)


@njit(cache=True, nogil=True)
def _returns(p: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Mask of the rows of ``p`` (N, 3) that are finite and not all zero (zeros are the invalid returns)."""
    keep = np.empty(p.shape[0], np.bool_)
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        keep[i] = np.isfinite(x) and np.isfinite(y) and np.isfinite(z) and (x != 0 or y != 0 or z != 0)
    return keep


def _crop(p: np.ndarray, params: IcpParams) -> np.ndarray:
    if params.max_range is None:
        return p
    return take_rows(p, np.einsum("ni,ni->n", p, p) <= params.max_range**2)


def _prepare(points: Any, params: IcpParams, voxel: float, role: str) -> IcpCloud:
    t0 = time.perf_counter()
    p = _crop(as_points(points, f"{role} scan"), params)
    if p.shape[0] < params.normal_neighbors:
        raise ScanDataError(
            f"{role} scan: {p.shape[0]} valid points, at least {params.normal_neighbors} needed"
        )
    native_tree = None
    if params.backend == "small_gicp":
        sg = _small_gicp()
        threads = prepare_threads(params)
        # small_gicp's one-call preparation makes the grid (its own block-wise one) and the search tree; with
        # more threads its normals / covariances are made from one neighbour (nearly free) and then remade on
        # `prepare_threads`: exact neighbours, one point at a time, so the same arrays as on one thread
        native, native_tree = sg.preprocess_points(
            p,
            downsampling_resolution=voxel,
            num_neighbors=params.normal_neighbors if threads == 1 else 1,
            num_threads=params.num_threads,
        )
        if threads > 1:
            sg.estimate_normals_covariances(native, native_tree, params.normal_neighbors, num_threads=threads)
        vox = np.asarray(native.points())[:, :3]
    else:
        o3d = _open3d()
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(params.normal_neighbors))
        vox = np.asarray(pcd.points)
        native = pcd
        if params.backend == "open3d_t":
            native = o3d.t.geometry.PointCloud.from_legacy(pcd)
    vox = np.ascontiguousarray(vox, dtype=np.float64)
    tree = None
    if role == "target":
        tree = native_tree if native_tree is not None else _small_gicp().KdTree(vox)
    ms = (time.perf_counter() - t0) * 1e3
    origin = p if role == "source" else None
    return IcpCloud(vox, role, params.backend, voxel, native, native_tree, tree, ms, origin=origin)


def prepare_threads(params: IcpParams) -> int:
    """The threads that prepare a cloud: ``params.prepare_threads``, else `placerec.threads.available_threads`."""
    return params.prepare_threads if params.prepare_threads is not None else available_threads()


def prepare_target(points: Any, params: IcpParams | None = None) -> IcpCloud:
    """The matched scan voxelised at ``voxel_size`` with normals and search trees."""
    params = params or IcpParams()
    return _prepare(points, params, params.voxel_size, "target")


def prepare_source(points: Any, params: IcpParams | None = None) -> IcpCloud:
    """The query scan voxelised at ``source_voxel_size`` (with normals / covariances for GICP)."""
    params = params or IcpParams()
    return _prepare(points, params, params.source_voxel_size, "source")


def coarser_source(source: IcpCloud, voxel: float | None, params: IcpParams) -> IcpCloud:
    """``source`` (a prepared query) voxelised again at the coarser ``voxel``, made once and kept on it; ``source``
    itself when ``voxel`` is None or not coarser, or when the coarser grid keeps too few voxels for normals."""
    if source.role != "source":
        raise ScanDataError(f"coarser_source needs a source cloud, got a {source.role} cloud")
    if voxel is None or voxel <= source.voxel_size or len(source) < params.normal_neighbors:
        return source
    if voxel not in source.derived:
        coarse = _prepare(source.points, params, voxel, "source")
        source.derived[voxel] = coarse if len(coarse) >= params.normal_neighbors else source
    return source.derived[voxel]


def finer_source(source: IcpCloud, voxel: float, params: IcpParams) -> IcpCloud:
    """``source`` (a prepared query) made again at the finer ``voxel`` from the points it was prepared from, made
    once and kept on it; ``source`` itself when ``voxel`` is not finer (or it keeps no points of its own)."""
    if source.role != "source":
        raise ScanDataError(f"finer_source needs a source cloud, got a {source.role} cloud")
    if voxel >= source.voxel_size or source.origin is None:
        return source
    if voxel not in source.derived:
        source.derived[voxel] = _prepare(source.origin, params, voxel, "source")
    return source.derived[voxel]


def alignment_stats(
    source: np.ndarray,
    target: IcpCloud,
    T: np.ndarray,
    fitness_distance: float,
    residual_max_range: float | None,
    max_points: int | None = None,
    constraint: bool = False,
) -> tuple[float, float, float, float]:
    """(fitness, rmse, residual, constraint) of ``source`` points moved by ``T`` against ``target`` (see module
    docstring), measured on at most ``max_points`` of them (evenly strided; None = all). ``constraint`` (only when
    asked, else NaN): how well the overlap pins the translation down, the smallest eigenvalue of the mean outer
    product of the unit normals of the target voxels the overlapping source points landed on (1/3 when the
    normals point every way evenly; ~0 when they leave a direction free, e.g. road and one facade along a
    street, where ICP can slide)."""
    if target.tree is None:
        raise ScanDataError("alignment_stats needs a cloud made by prepare_target")
    if max_points is not None and len(source) > max_points:
        source = source[:: -(-len(source) // max_points)]
    moved = source @ T[:3, :3].T + T[:3, 3]
    nearest, sq = target.tree.batch_nearest_neighbor_search(np.ascontiguousarray(moved))
    d = np.sqrt(np.asarray(sq, dtype=np.float64))
    close = d <= fitness_distance
    n = max(len(d), 1)
    fitness = float(close.sum()) / n
    rmse = float(np.sqrt(np.mean(d[close] ** 2))) if close.any() else float("inf")
    dr = d if residual_max_range is None else d[d <= residual_max_range]
    residual = float(np.mean(dr**2)) if dr.size else float("inf")
    pinned = math.nan
    if constraint:
        pinned = normal_spread(target_normals(target)[np.asarray(nearest, dtype=np.int64)[close]])
    return fitness, rmse, residual, pinned


def target_normals(target: IcpCloud) -> np.ndarray:
    """The target voxels' normals (M, 3), as the backend estimated them when the cloud was prepared (zero where a
    voxel had too few neighbours)."""
    if target.backend == "small_gicp":
        return np.asarray(target.native.normals(), dtype=np.float64)[:, :3]
    if target.backend == "open3d":
        return np.asarray(target.native.normals, dtype=np.float64)
    return np.asarray(target.native.point.normals.numpy(), dtype=np.float64)


def normal_spread(normals: np.ndarray) -> float:
    """The smallest eigenvalue of the mean outer product of the unit ``normals`` (N, 3) (zero vectors left out):
    1/3 for normals spread evenly in every direction, 0 when none has a component along some direction; 0 for no
    normals."""
    length = np.linalg.norm(normals, axis=1)
    unit = normals[length > 1e-9] / length[length > 1e-9, None]
    if unit.shape[0] == 0:
        return 0.0
    return float(max(np.linalg.eigvalsh(unit.T @ unit / unit.shape[0])[0], 0.0))


def refine(
    source: IcpCloud,
    target: IcpCloud,
    init: np.ndarray,
    params: IcpParams | None = None,
    fitness_distance: float = 0.5,
    residual_max_range: float | None = None,
    constraint: bool = False,
) -> IcpResult:
    """ICP of ``source`` onto ``target`` from ``init`` (T_target_source, 4x4); see the module docstring. With
    ``constraint`` the result's ``constraint`` is measured too (`alignment_stats`)."""
    params = params or IcpParams()
    if source.role != "source" or target.role != "target":
        raise ScanDataError(f"refine needs a source and a target cloud, got {source.role} and {target.role}")
    if source.backend != params.backend or target.backend != params.backend:
        raise ScanDataError(
            f"clouds prepared for {source.backend}/{target.backend}, ICP backend is {params.backend}"
        )
    T0 = np.asarray(init, dtype=np.float64)
    if T0.shape != (4, 4) or not np.isfinite(T0).all():
        raise ScanDataError(f"initial pose must be a finite 4x4 matrix, got shape {T0.shape}")
    t0 = time.perf_counter()
    if params.backend == "small_gicp":
        sg = _small_gicp()
        res = sg.align(
            target.native,
            source.native,
            target.native_tree,
            init_T_target_source=T0,
            registration_type="PLANE_ICP" if params.method == "plane" else "GICP",
            max_correspondence_distance=params.max_correspondence_distance,
            num_threads=params.num_threads,
            max_iterations=params.max_iterations,
        )
        T, iters = np.asarray(res.T_target_source, dtype=np.float64), int(res.iterations)
    elif params.backend == "open3d":
        reg = _open3d().pipelines.registration
        res = reg.registration_icp(
            source.native,
            target.native,
            params.max_correspondence_distance,
            T0,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=params.max_iterations),
        )
        T, iters = np.asarray(res.transformation, dtype=np.float64), -1
    else:
        o3d = _open3d()
        treg = o3d.t.pipelines.registration
        res = treg.icp(
            source.native,
            target.native,
            params.max_correspondence_distance,
            o3d.core.Tensor(T0),
            treg.TransformationEstimationPointToPlane(),
            treg.ICPConvergenceCriteria(max_iteration=params.max_iterations),
        )
        T, iters = res.transformation.numpy().astype(np.float64), int(res.num_iterations)
    fitness, rmse, residual, pinned = alignment_stats(
        source.points, target, T, fitness_distance, residual_max_range, params.stats_points, constraint
    )
    ms = (time.perf_counter() - t0) * 1e3  # ICP and its statistics
    return IcpResult(T, fitness, rmse, residual, iters, ms, pinned)


def _small_gicp() -> Any:
    try:
        return import_openmp("small_gicp")
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError(
            "ICP backend 'small_gicp' needs the small_gicp package: pip install small_gicp"
        ) from exc


def _open3d() -> Any:
    try:
        import open3d
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError("ICP backend 'open3d' needs the open3d package: pip install open3d") from exc
    return open3d
