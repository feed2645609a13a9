"""Online place aggregation: the scans added within a trailing window of travelled distance, merged as a place.

With ``places.window_m > 0`` a 3D pipeline keeps, for every added scan, its pose, the distance travelled up to
it and its voxelised cloud with intensity; an entry is then described from the clouds of the scans within that
much travel before it (causal, so it works in loop mode), merged in the entry's frame (a place of the ISHOT
paper, Sec. IV-B). The window is part of a saved database (`arrays`, `PlaceWindow.from_arrays`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from placerec.errors import ArtifactError, ScanDataError, short_repr
from placerec.io.artifact_schema import Member, check_counts, check_unique
from placerec.three_d.places import merge_clouds
from placerec.types import Description, Scan

__all__ = ["PlaceWindow", "WINDOW_SCHEMA"]

#: the saved arrays of a window: its scans' ids, poses, travelled distance and per-scan counts of cloud points
WINDOW_SCHEMA = {
    "buffer_ids": Member("iu", ("n_buffer",)),
    "buffer_poses": Member("f", ("n_buffer", 4, 4), finite=True),
    "buffer_travelled": Member("f", ("n_buffer",), finite=True),
    "buffer_counts": Member("iu", ("n_buffer",), min_value=0),
    "buffer_xyz": Member("f", ("n_points", 3), finite=True),
    "buffer_intensity": Member("f", ("n_points",), finite=True),
}


class PlaceWindow:
    """The trailing window of (id, pose, travelled distance, cloud xyz, cloud intensity) of the added scans."""

    def __init__(self, window_m: float, name: str) -> None:
        self.window_m = window_m
        self.name = name
        self.scans: list[tuple[int, np.ndarray, float, np.ndarray, np.ndarray]] = []
        self.travelled = 0.0

    def push(self, scan_id: int, T: np.ndarray, description: Description) -> None:
        """Add a scan (its description's ``cloud_xyz`` / ``cloud_intensity``) and drop those beyond the window."""
        if "cloud_xyz" not in description:
            raise ScanDataError(f"{self.name}: description without a cloud (made with place_window_m = 0?)")
        if self.scans:
            self.travelled += float(np.linalg.norm(T[:3, 3] - self.scans[-1][1][:3, 3]))
        self.scans.append(
            (scan_id, T, self.travelled, description["cloud_xyz"], description["cloud_intensity"])
        )
        while self.scans and self.travelled - self.scans[0][2] > self.window_m:
            self.scans.pop(0)

    def cloud(self, T_world_place: np.ndarray) -> Scan:
        """The window's scans merged in the frame ``T_world_place``."""
        return merge_clouds(T_world_place, [(T, Scan(pts, it)) for _, T, _, pts, it in self.scans], "place")

    def arrays(self) -> dict[str, np.ndarray]:
        buf = self.scans
        return {
            "buffer_ids": np.asarray([b[0] for b in buf], np.int64),
            "buffer_poses": np.asarray([b[1] for b in buf], np.float64).reshape(-1, 4, 4),
            "buffer_travelled": np.asarray([b[2] for b in buf], np.float64),
            "buffer_counts": np.asarray([b[3].shape[0] for b in buf], np.int64),
            "buffer_xyz": _cat([b[3] for b in buf], (0, 3)),
            "buffer_intensity": _cat([b[4] for b in buf], (0,)),
        }

    def restore(self, path: Any, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> None:
        """Replace the window by a saved one (`arrays` checked against `WINDOW_SCHEMA`); `ArtifactError` when the
        ids repeat, the counts do not add up or the distances are not distances."""
        check_unique(arrays["buffer_ids"], path, "buffer_ids")
        check_counts(arrays["buffer_counts"], arrays["buffer_xyz"].shape[0], path, "buffer_counts")
        travelled = meta.get("travelled", 0.0)
        along = arrays["buffer_travelled"]
        if (
            not isinstance(travelled, int | float)
            or isinstance(travelled, bool)
            or not 0 <= travelled < np.inf
            or (along.size and (along.min() < 0 or along.max() > travelled or (np.diff(along) < 0).any()))
        ):
            raise ArtifactError(
                f"{path}: 'travelled' {short_repr(travelled)} and 'buffer_travelled' must be distances: finite, "
                ">= 0, non-decreasing along the buffer and at most 'travelled'"
            )
        cuts = np.cumsum(arrays["buffer_counts"])[:-1]
        n = len(arrays["buffer_ids"])
        self.scans = list(
            zip(
                (int(i) for i in arrays["buffer_ids"]),
                arrays["buffer_poses"],
                (float(t) for t in arrays["buffer_travelled"]),
                np.split(arrays["buffer_xyz"], cuts) if n else [],
                np.split(arrays["buffer_intensity"], cuts) if n else [],
                strict=False,
            )
        )
        self.travelled = float(travelled)


def _cat(parts: list[np.ndarray], empty: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(parts).astype(np.float32) if parts else np.zeros(empty, np.float32)
