"""A simulated world: one Open3D ray-casting scene plus what textures, routes and clutter need to know about it.

`build_world(preset, seed)` runs a preset builder (`placerec.sim.presets`) and finalises its mesh into an
``o3d.t.geometry.RaycastingScene``. Worlds are cached in-process per (preset, seed): every scan of every sequence
over the same world reuses the same scene. The hit primitive id indexes ``tri_material`` and ``tri_object``; the
object id indexes the object frames, parameter rows and seeds used by the textures. Ground triangles carry the
placeholder material `M.GROUND`; their real material is read from the ground raster at the hit's (x, y).
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from placerec.errors import DependencyError
from placerec.sim.geometry import MeshArrays
from placerec.sim.jit import elementwise, inline, njit

__all__ = [
    "World",
    "GroundMap",
    "RoadGraph",
    "Terrain",
    "FreeSpace",
    "PresetResult",
    "build_world",
    "finalise_world",
    "world_from_mesh",
]

log = logging.getLogger(__name__)


@dataclass
class GroundMap:
    """A raster of material ids covering the world's ground (cells of ``resolution`` metres)."""

    labels: np.ndarray  # (H, W) uint8, row = y, column = x
    x0: float
    y0: float
    resolution: float

    def lookup(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Material ids at world points (x, y); points outside the raster take the nearest edge cell."""
        return elementwise(
            _ground_label_n, (x, y), (np.float32, np.float32), np.uint8, self.labels, self.geometry()
        )

    def geometry(self) -> tuple[float, float, float]:
        """(x0, y0, resolution) as the compiled kernels read it."""
        return (float(self.x0), float(self.y0), float(self.resolution))


@inline
def ground_cell_1(geometry: tuple, shape: tuple, x: float, y: float) -> tuple[int, int]:
    """(row, column) of the ground raster cell under (x, y), clamped to the raster (``geometry`` =
    `GroundMap.geometry`, ``shape`` = the raster's shape)."""
    ix = min(max(np.int64((x - geometry[0]) / geometry[2]), 0), shape[1] - 1)
    iy = min(max(np.int64((y - geometry[1]) / geometry[2]), 0), shape[0] - 1)
    return iy, ix


@njit
def _ground_label_n(x, y, labels, geometry, out):
    for i in range(out.shape[0]):
        iy, ix = ground_cell_1(geometry, labels.shape, x[i], y[i])
        out[i] = labels[iy, ix]


@dataclass
class FreeSpace:
    """A boolean raster: True where a sensor (vehicle or pole) can stand, away from obstacles."""

    mask: np.ndarray  # (H, W) bool, row = y
    x0: float
    y0: float
    resolution: float

    def is_free(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        h, w = self.mask.shape
        ix = ((np.asarray(x) - self.x0) / self.resolution).astype(np.int64)
        iy = ((np.asarray(y) - self.y0) / self.resolution).astype(np.int64)
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        return inside & self.mask[np.clip(iy, 0, h - 1), np.clip(ix, 0, w - 1)]


@dataclass
class Terrain:
    """Ground height: flat (no components) or a sum of smooth sinusoids."""

    amplitude: np.ndarray = field(default_factory=lambda: np.zeros(0))
    kx: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ky: np.ndarray = field(default_factory=lambda: np.zeros(0))
    phase: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = np.zeros(np.broadcast(x, y).shape)
        for a, kx, ky, ph in zip(self.amplitude, self.kx, self.ky, self.phase, strict=True):
            z = z + a * np.sin(kx * x + ky * y + ph)
        return z


@dataclass
class RoadGraph:
    """A grid-shaped network of streets or paths: node (i, j) at ``nodes[i, j]``; edges between 4-neighbours.

    ``edges`` maps a node pair (in either order) to its centre-line polyline from the first node to the second.
    ``lanes`` gives the lanes per direction of an edge (default 1); ``anchor`` is the node the default route
    starts from (the preset puts small blocks around it so the default route is short).
    """

    nodes: np.ndarray  # (I, J, 2)
    edges: dict[tuple[tuple[int, int], tuple[int, int]], np.ndarray]
    lane_width: float
    anchor: tuple[int, int]
    lanes: dict[tuple[tuple[int, int], tuple[int, int]], int] = field(default_factory=dict)

    def has_edge(self, a: tuple[int, int], b: tuple[int, int]) -> bool:
        return (a, b) in self.edges or (b, a) in self.edges

    def polyline(self, a: tuple[int, int], b: tuple[int, int]) -> np.ndarray:
        if (a, b) in self.edges:
            return self.edges[(a, b)]
        return self.edges[(b, a)][::-1]

    def n_lanes(self, a: tuple[int, int], b: tuple[int, int]) -> int:
        return self.lanes.get((a, b), self.lanes.get((b, a), 1))

    def neighbours(self, a: tuple[int, int]) -> list[tuple[int, int]]:
        i, j = a
        out = []
        for b in ((i + 1, j), (i, j + 1), (i - 1, j), (i, j - 1)):
            if self.has_edge(a, b):
                out.append(b)
        return out


@dataclass
class PresetResult:
    """What a preset builder returns (see `placerec.sim.presets`)."""

    mesh: MeshArrays
    ground: GroundMap
    terrain: Terrain
    roads: RoadGraph
    free: FreeSpace
    lanes: np.ndarray  # (L, 2, 2) straight lane segments for moving cars, start -> end = travel direction
    walkways: np.ndarray  # (S, 2, 2) segments pedestrians walk along
    parking_slots: np.ndarray  # (P, 3) x, y, yaw of free kerbside slots (transient parked cars)
    bounds: tuple[float, float, float, float]
    info: dict = field(default_factory=dict)


@dataclass
class World:
    """A built world (see the module docstring). Use `build_world` to get one."""

    preset: str
    seed: int
    scene: object  # o3d.t.geometry.RaycastingScene
    tri_material: np.ndarray
    tri_object: np.ndarray
    obj_rot: np.ndarray
    obj_origin: np.ndarray
    obj_params: np.ndarray
    obj_seed: np.ndarray
    ground: GroundMap
    terrain: Terrain
    roads: RoadGraph
    free: FreeSpace
    lanes: np.ndarray
    walkways: np.ndarray
    parking_slots: np.ndarray
    bounds: tuple[float, float, float, float]
    n_triangles: int
    build_seconds: float
    info: dict = field(default_factory=dict)
    cache: dict = field(default_factory=dict, repr=False)

    @property
    def n_objects(self) -> int:
        return int(self.obj_seed.shape[0])

    def __reduce__(self) -> tuple:
        # the ray-casting scene cannot be pickled; a preset world is rebuilt (deterministically) on unpickling
        from placerec.sim.presets import PRESETS

        if self.preset not in PRESETS:
            raise TypeError(f"world {self.preset!r} is not a preset and cannot be pickled")
        return (build_world, (self.preset, self.seed))

    def ground_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.terrain.height(x, y)


def make_scene(vertices: np.ndarray, triangles: np.ndarray) -> object:
    """An Open3D tensor ray-casting scene over one triangle mesh."""
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - open3d is a hard dependency
        raise DependencyError("the simulator needs open3d (pip install open3d)") from exc
    scene = o3d.t.geometry.RaycastingScene()
    if len(triangles):
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32)),
        )
    return scene


def finalise_world(preset: str, seed: int, res: PresetResult, t0: float) -> World:
    m = res.mesh
    scene = make_scene(m.vertices, m.triangles)
    world = World(
        preset=preset,
        seed=seed,
        scene=scene,
        tri_material=m.tri_material,
        tri_object=m.tri_object,
        obj_rot=m.obj_rot,
        obj_origin=m.obj_origin,
        obj_params=m.obj_params,
        obj_seed=m.obj_seed,
        ground=res.ground,
        terrain=res.terrain,
        roads=res.roads,
        free=res.free,
        lanes=res.lanes,
        walkways=res.walkways,
        parking_slots=res.parking_slots,
        bounds=res.bounds,
        n_triangles=int(m.triangles.shape[0]),
        build_seconds=time.perf_counter() - t0,
        info=res.info,
    )
    log.debug(
        "built world %s seed %d: %d triangles, %d objects in %.2f s",
        preset,
        seed,
        world.n_triangles,
        world.n_objects,
        world.build_seconds,
    )
    return world


def world_from_mesh(mesh: MeshArrays, name: str = "custom", ground_material: int = 2) -> World:
    """A minimal world around a hand-made mesh (for constructed test scenes): flat ground raster of one material,
    no roads, no lanes, everything free."""
    t0 = time.perf_counter()
    res = PresetResult(
        mesh=mesh,
        ground=GroundMap(np.full((1, 1), ground_material, np.uint8), 0.0, 0.0, 1.0),
        terrain=Terrain(),
        roads=RoadGraph(nodes=np.zeros((1, 1, 2)), edges={}, lane_width=3.5, anchor=(0, 0)),
        free=FreeSpace(np.ones((1, 1), bool), -1e6, -1e6, 2e6),
        lanes=np.zeros((0, 2, 2)),
        walkways=np.zeros((0, 2, 2)),
        parking_slots=np.zeros((0, 3)),
        bounds=(-1e3, -1e3, 1e3, 1e3),
    )
    return finalise_world(name, 0, res, t0)


@functools.lru_cache(maxsize=6)
def _cached_world(preset: str, seed: int) -> World:
    from placerec.sim.presets import get_preset

    builder: Callable[[int], PresetResult] = get_preset(preset)
    t0 = time.perf_counter()
    return finalise_world(preset, seed, builder(seed), t0)


def build_world(preset: str | World = "town", seed: int = 0) -> World:
    """The world of a preset (``town``, ``campus``/``park``, ``industrial``) for a seed, cached per process."""
    if isinstance(preset, World):
        return preset
    from placerec.sim.presets import canonical_preset

    return _cached_world(canonical_preset(preset), int(seed))
