"""The town preset (`placerec.sim.preset_town.build_town`): the world a seed makes is fixed.

The fingerprint holds what the random draws decide exactly on any platform (block sizes, how many blocks are
built and reused, the mesh's topology, materials and object seeds, the lanes, walkways and parking slots), so a
change of the order of the draws or of a building step shows here. Vertices and rasters are left out: their last
bits follow the platform's trigonometry.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from placerec.sim.preset_town import build_town

FINGERPRINTS = {
    0: {
        "block_x": [71.09509, 75.602399, 40.620285, 38.413364, 52.90621, 66.365139, 62.283822],
        "block_y": [65.490154, 45.602494, 41.991487, 51.1888, 64.473809, 65.308997],
        "blocks": (32, 6),
        "shapes": ((71386, 3), (103362, 3), (208, 2, 2), (388, 2, 2), (335, 3)),
        "edges": 97,
        "topology": "ce582844da49263e",
    },
    3: {
        "block_x": [65.719979, 70.808572, 38.849537, 43.683825, 63.686298, 61.127863, 56.981234],
        "block_y": [73.575901, 47.904905, 41.397239, 50.370498, 50.596341, 56.063193],
        "blocks": (36, 4),
        "shapes": ((83399, 3), (125608, 3), (208, 2, 2), (388, 2, 2), (344, 3)),
        "edges": 97,
        "topology": "284b1ef11e29a4ef",
    },
}


@pytest.mark.parametrize("seed", sorted(FINGERPRINTS))
def test_the_town_of_a_seed_is_fixed(seed):
    want = FINGERPRINTS[seed]
    world = build_town(seed)
    mesh, info = world.mesh, world.info
    assert np.round(info["block_x"], 6).tolist() == want["block_x"]
    assert np.round(info["block_y"], 6).tolist() == want["block_y"]
    assert (info["n_building_blocks"], info["n_reused_blocks"]) == want["blocks"]
    shapes = (mesh.vertices.shape, mesh.triangles.shape, world.lanes.shape, world.walkways.shape,
              world.parking_slots.shape)  # fmt: skip
    assert shapes == want["shapes"] and len(world.roads.edges) == want["edges"]
    arrays = (mesh.triangles, mesh.tri_material, mesh.tri_object, mesh.obj_seed)
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest()[:16]
    assert digest == want["topology"]
