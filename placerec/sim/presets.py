"""Registry of world presets: name -> builder ``(seed) -> PresetResult``.

* ``town`` — street grid, row houses with textured facades, sidewalks and kerbs, road markings and crosswalks,
  poles, signs, parked cars, fences, trees, small parks and parking lots (`placerec.sim.preset_town`).
* ``campus`` (alias ``park``) — unstructured: rolling grass terrain, tree groups and forest patches, bushes,
  hedges, curved paths, a few large buildings and parking lots (`placerec.sim.preset_campus`); the kind of
  place the ISHOT paper targets.
* ``industrial`` — large corrugated sheds with roller doors, container stacks, open concrete yards with heaps,
  pallets and trucks, chain-link fences, tanks and light masts (`placerec.sim.preset_industrial`).
"""

from __future__ import annotations

from collections.abc import Callable

from placerec.errors import ConfigError
from placerec.sim.site import PresetResult

__all__ = ["PRESETS", "get_preset", "preset_names", "canonical_preset"]


def _town(seed: int) -> PresetResult:
    from placerec.sim.preset_town import build_town

    return build_town(seed)


def _campus(seed: int) -> PresetResult:
    from placerec.sim.preset_campus import build_campus

    return build_campus(seed)


def _industrial(seed: int) -> PresetResult:
    from placerec.sim.preset_industrial import build_industrial

    return build_industrial(seed)


PRESETS: dict[str, Callable[[int], PresetResult]] = {
    "town": _town,
    "campus": _campus,
    "industrial": _industrial,
}
_ALIASES = {"park": "campus", "city": "town", "urban": "town"}


def preset_names() -> list[str]:
    """Names of the world presets (aliases not included)."""
    return sorted(PRESETS)


def canonical_preset(name: str) -> str:
    key = str(name).lower()
    key = _ALIASES.get(key, key)
    if key not in PRESETS:
        raise ConfigError(
            f"sim.world: unknown world preset {name!r}; allowed: {preset_names() + sorted(_ALIASES)}"
        )
    return key


def get_preset(name: str) -> Callable[[int], PresetResult]:
    """The builder of a preset (accepts aliases such as ``park``)."""
    return PRESETS[canonical_preset(name)]
