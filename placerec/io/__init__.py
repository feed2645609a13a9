"""Reading and writing scans, trajectories and sequences.

Scan formats (`SCAN_READERS`): ``kitti`` (``.bin``), ``nclt`` (``.bin``, recognised by its bytes), ``pcd``,
``ply``, ``npy``, ``npz``; writers (`SCAN_WRITERS`): kitti, pcd, ply, npz. Sequences: `KittiSequence`,
`FolderSequence`, `placerec.io.rosbag.RosbagSequence` (needs ``rosbags``), `placerec.io.ouster.OusterSequence`
(needs ``ouster-sdk``); `open_sequence` picks one. The optional dependencies are imported only when used.
"""

from __future__ import annotations

from placerec.io.poses import read_poses, write_kitti_poses, write_tum_poses
from placerec.io.registry import EXTENSIONS, SCAN_READERS, SCAN_WRITERS, read_scan, write_scan
from placerec.io.sequences import FolderSequence, KittiSequence, load_sensor_yaml, open_sequence

__all__ = [
    "read_scan",
    "write_scan",
    "read_poses",
    "write_kitti_poses",
    "write_tum_poses",
    "open_sequence",
    "KittiSequence",
    "FolderSequence",
    "load_sensor_yaml",
    "SCAN_READERS",
    "SCAN_WRITERS",
    "EXTENSIONS",
]
