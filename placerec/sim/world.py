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
from placerec.sim.presets import PRESETS, canonical_preset, get_preset
from placerec.sim.site import FreeSpace, GroundMap, PresetResult, RoadGraph, Terrain

__all__ = ["World", "build_world", "finalise_world", "make_scene", "world_from_mesh"]

log = logging.getLogger(__name__)


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
        # open3d's stubs make Tensor's dtype and device required
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),  # type: ignore[call-overload]
            o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32)),  # type: ignore[call-overload]
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
    builder: Callable[[int], PresetResult] = get_preset(preset)
    t0 = time.perf_counter()
    return finalise_world(preset, seed, builder(seed), t0)


def build_world(preset: str | World = "town", seed: int = 0) -> World:
    """The world of a preset (``town``, ``campus``/``park``, ``industrial``) for a seed, cached per process."""
    if isinstance(preset, World):
        return preset
    return _cached_world(canonical_preset(preset), int(seed))
