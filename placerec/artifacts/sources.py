"""Where a builder's scans come from: sequences on disk or a simulated world, never both.

A sequence on disk is anything `placerec.io.open_sequence` reads (``format`` and ``poses`` are its options); a
simulated world (`SimWorld`) gives a whole route (`SimWorld.route`), the map of its localisation split
(`SimWorld.localization_map`) or a split with query scans (`SimWorld.localization_split`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import Field

from placerec.errors import ConfigError
from placerec.params import Params
from placerec.types import Sequence

if TYPE_CHECKING:
    from placerec.sim.localization import LocalizationSplit

__all__ = ["FilePath", "SimWorld", "SequenceSource", "require_one_source", "open_path"]

#: A file or folder path; a string is accepted too.
FilePath = Annotated[Path, Field(strict=False)]


class SimWorld(Params):
    """A world of the simulator (`placerec.sim`) as the source of scans."""

    world: str = Field(description="world preset: town, campus, industrial")
    sensor: str = Field("vlp16", description="simulated sensor")
    scans: int | None = Field(None, description="scans of the route or of the map (None: the whole route)")
    seed: int = Field(0, description="world and noise seed")
    rate_hz: float | None = Field(
        None, gt=0, le=1000, description="frames a second along the route (None: one scan a metre)"
    )
    sweep_motion: bool = Field(False, description="each ray measured from the pose at its own time (moving)")

    def route(self) -> Sequence:
        """The scans along the world's default route."""
        from placerec.sim import SimulatedSequence

        return SimulatedSequence(world=self.world, sensor=self.sensor, n_scans=self.scans, seed=self.seed,
                                 rate_hz=self.rate_hz, sweep_motion=self.sweep_motion)  # fmt: skip

    def localization_split(
        self, n_queries: int, draw: int = 0, conditions: tuple[str, ...] | None = None
    ) -> LocalizationSplit:
        """The map (``scans`` scans) and ``n_queries`` query scans per condition (all conditions when None) of
        draw ``draw`` (`placerec.sim.make_localization_split`)."""
        from placerec.sim import make_localization_split

        extra: dict[str, Any] = {} if conditions is None else {"conditions": conditions}
        return make_localization_split(
            self.world, self.sensor, self.seed, n_queries, n_map=self.scans, draw=draw, **extra
        )

    def localization_map(self) -> Sequence:
        """The map sequence of the world's localisation split."""
        return self.localization_split(1, conditions=()).map


def require_one_source(given: bool, sim: SimWorld | None, what: str = "a SEQUENCE path") -> None:
    """`ConfigError` unless exactly one of ``what`` (``given``: whether it was) and a simulated world is given."""
    if given == (sim is not None):
        raise ConfigError(f"give either {what} or --sim-world (not both)")


def open_path(path: str | Path, format: str | None = None, poses: str | Path | None = None) -> Sequence:
    """The sequence at ``path`` (`placerec.io.open_sequence`, with ``format`` and ``poses`` when given)."""
    from placerec.io import open_sequence

    options: dict[str, Any] = {k: v for k, v in (("format", format), ("poses", poses)) if v is not None}
    return open_sequence(path, **options)


class SequenceSource(Params):
    """One sequence: a path (with an optional reader ``format`` and ``poses`` file) or a simulated world."""

    path: FilePath | None = Field(None, description="a sequence (anything `placerec info` reads)")
    format: str | None = Field(None, description="force a reader, e.g. 'kitti'")
    poses: FilePath | None = Field(None, description="poses file (default: the sequence's own)")
    sim: SimWorld | None = None

    def check(self) -> SequenceSource:
        """This source, once checked to name exactly one of a path and a simulated world (else `ConfigError`)."""
        require_one_source(self.path is not None, self.sim)
        return self

    def route(self) -> Sequence:
        """The sequence at ``path``, or the simulated world's route."""
        self.check()
        return self.sim.route() if self.sim is not None else self._open_path()

    def localization_map(self) -> Sequence:
        """The sequence at ``path``, or the map of the simulated world's localisation split."""
        self.check()
        if self.sim is not None:
            return self.sim.localization_map()
        return self._open_path()

    def _open_path(self) -> Sequence:
        assert self.path is not None  # `check`: a path when there is no simulated world
        return open_path(self.path, self.format, self.poses)
