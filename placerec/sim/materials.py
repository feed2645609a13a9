"""Materials: near-infrared diffuse reflectance plus procedural textures evaluated at the hit points.

Reflectances are for the 850-905 nm band of automotive LiDARs: asphalt is dark (~0.1), concrete and brick
medium (0.3-0.4), vegetation bright (0.4-0.55, leaves reflect NIR strongly), white paint bright (0.55-0.7).
Retro-reflective sheeting (signs, licence plates, road studs, rear reflectors) has an effective reflectance well
above 1 and saturates the sensor.

A texture function (`placerec.sim.textures`) receives a `Hits` batch (world point, point and normal in the hit object's local frame, the
object's parameter row and seed, and the beam footprint) and returns a `Shade`: reflectance, an optional extra
dropout probability (window glass, chain-link fences, foliage gaps) and an optional extra range (beams that
penetrate foliage). Thin features (mortar joints, tile gaps, ribs) are box-filtered by the footprint, so their
contrast fades with range as on a real sensor.

Object parameter rows (``PARAM_COUNT`` floats) use the indices ``P_HX, P_HY, P_H`` (half length, half width and
height of the object's box, local frame origin at the centre of its base), ``P_TONE`` (base reflectance, 0 = the
material's default), ``P_A..P_D`` (material-specific) and ``P_STYLE``, ``P_FLAGS``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

__all__ = [
    "M",
    "Material",
    "MATERIALS",
    "Hits",
    "Shade",
    "PARAM_COUNT",
    "SPECULAR",
    "LAMBERT",
    "P_HX",
    "P_HY",
    "P_H",
    "P_TONE",
    "P_A",
    "P_B",
    "P_C",
    "P_D",
    "P_STYLE",
    "P_FLAGS",
]

PARAM_COUNT = 10
P_HX, P_HY, P_H, P_TONE, P_A, P_B, P_C, P_D, P_STYLE, P_FLAGS = range(PARAM_COUNT)


class M(IntEnum):
    """Material ids (stored per triangle and in the ground raster)."""

    NONE = 0
    GROUND = 1  # placeholder: the material comes from the world's ground raster
    ASPHALT = 2
    ASPHALT_PATCH = 3
    MARKING = 4
    ROAD_STUD = 5
    PAVING = 6
    CURB = 7
    GRASS = 8
    GRAVEL = 9
    DIRT = 10
    CONCRETE = 11
    MANHOLE = 12
    FACADE = 13
    ROOF = 14
    METAL = 15
    SIGN = 16
    CAR = 17
    CAR_GLASS = 18
    RUBBER = 19
    BARK = 20
    FOLIAGE = 21
    CORRUGATED = 22
    FENCE = 23
    PERSON = 24
    WOOD = 25
    STONE = 26
    GLASS = 27


@dataclass(frozen=True)
class Material:
    """Static properties of a material; the texture refines the reflectance per hit."""

    name: str
    reflectance: float
    specular: float = 0.0
    dropout: float = 0.0
    texture: str = "plain"
    lambert: float = 1.0  # exponent k of cos(incidence)^k: 1 Lambertian, < 1 rough surfaces that backscatter


MATERIALS: dict[M, Material] = {
    M.NONE: Material("none", 0.0),
    M.GROUND: Material("ground", 0.2),
    M.ASPHALT: Material("asphalt", 0.10, texture="asphalt", lambert=0.6),
    M.ASPHALT_PATCH: Material("asphalt_patch", 0.065, texture="asphalt", lambert=0.6),
    M.MARKING: Material("road_marking", 0.60, texture="marking", lambert=0.8),
    M.ROAD_STUD: Material("road_stud", 150.0),
    M.PAVING: Material("paving", 0.30, texture="paving", lambert=0.8),
    M.CURB: Material("curb", 0.40, texture="rough", lambert=0.8),
    M.GRASS: Material("grass", 0.42, texture="grass", lambert=0.6),
    M.GRAVEL: Material("gravel", 0.28, texture="rough", lambert=0.6),
    M.DIRT: Material("dirt", 0.20, texture="rough", lambert=0.6),
    M.CONCRETE: Material("concrete", 0.30, texture="concrete", lambert=0.8),
    M.MANHOLE: Material("manhole", 0.18, specular=0.1, texture="manhole"),
    M.FACADE: Material("facade", 0.35, texture="facade"),
    M.ROOF: Material("roof", 0.12, texture="rough"),
    M.METAL: Material("metal", 0.30, specular=0.25, texture="rough"),
    M.SIGN: Material("sign", 200.0, texture="sign"),
    M.CAR: Material("car_paint", 0.35, specular=0.35, texture="car"),
    M.CAR_GLASS: Material("car_glass", 0.06, specular=0.6, dropout=0.45),
    M.RUBBER: Material("rubber", 0.05),
    M.BARK: Material("bark", 0.22, texture="rough"),
    M.FOLIAGE: Material("foliage", 0.45, dropout=0.12, texture="foliage", lambert=0.8),
    M.CORRUGATED: Material("corrugated_metal", 0.30, specular=0.15, texture="corrugated"),
    M.FENCE: Material("fence", 0.32, texture="fence"),
    M.PERSON: Material("person", 0.35, texture="person"),
    M.WOOD: Material("wood", 0.30, texture="wood"),
    M.STONE: Material("stone", 0.25, texture="rough"),
    M.GLASS: Material("glass", 0.05, specular=0.5, dropout=0.8),
}

N_MATERIALS = len(M)
_BASE = np.array([MATERIALS[M(i)].reflectance for i in range(N_MATERIALS)], dtype=np.float32)
SPECULAR = np.array([MATERIALS[M(i)].specular for i in range(N_MATERIALS)], dtype=np.float32)
DROPOUT = np.array([MATERIALS[M(i)].dropout for i in range(N_MATERIALS)], dtype=np.float32)
LAMBERT = np.array([MATERIALS[M(i)].lambert for i in range(N_MATERIALS)], dtype=np.float32)


@dataclass
class Hits:
    """A batch of hits on one material."""

    pw: np.ndarray  # (n, 3) float32 world point
    pl: np.ndarray  # (n, 3) float32 point in the object frame
    nl: np.ndarray  # (n, 3) float32 normal in the object frame
    params: np.ndarray  # (n, PARAM_COUNT) float32
    seed: np.ndarray  # (n,) uint32 object seed
    footprint: np.ndarray  # (n,) float32 beam footprint diameter (m)
    material: int

    def __len__(self) -> int:
        return int(self.pw.shape[0])

    def tone(self) -> np.ndarray:
        t = self.params[:, P_TONE]
        return np.where(t > 0, t, _BASE[self.material]).astype(np.float32)


@dataclass
class Shade:
    reflectance: np.ndarray
    dropout: np.ndarray | None = None
    depth: np.ndarray | None = None
