"""The site plan a world preset builds, before it becomes a ray-casting scene (`placerec.sim.world`).

`PresetResult` bundles the mesh with the ground material raster (`GroundMap`), the terrain height (`Terrain`),
the road network (`RoadGraph`) and where a sensor may stand (`FreeSpace`); routes, clutter and the renderer read
these through the built `World`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from placerec.sim.geometry import MeshArrays
from placerec.sim.jit import elementwise, inline, njit

__all__ = ["GroundMap", "FreeSpace", "Terrain", "RoadGraph", "PresetResult", "ground_cell_1"]


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
