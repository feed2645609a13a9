"""A sanity check of a loaded SuperPoint network on a built-in probe image, before it describes anything.

Whatever vouches for a model's files (the shipped hashes, its provenance, ``trust_model``), the network that will
run is run once on `probe_image` and its outputs are checked (`check_outputs`): the shapes its architecture says
(65 detector channels, ``descriptor_dim`` descriptor channels, one cell per 8x8 pixels), finite values of a
plausible size (``cv2.dnn`` turns a NaN into ~1e37 in its ReLU), a detector that responds to the image (its logits vary between cells) and descriptors that are not all the same (their
directions vary between cells). A model that fails is refused with `ArtifactError` naming it: a NaN bias, an ONNX
model of another descriptor size than its weights' header (which would otherwise fail late, in the vocabulary),
a network whose output is constant.

The checks cost one forward pass on a 64 x 256 image (~8 ms through ``cv2.dnn``); the extractor runs them once per
model, backend and file hashes in a process.
"""

from __future__ import annotations

import functools

import numpy as np

from placerec.errors import ArtifactError
from placerec.features.superpoint.arch import CELL, DETECTOR_CHANNELS, SuperPointArch

__all__ = ["PROBE_SHAPE", "probe_image", "check_outputs"]

#: rows, columns of the probe image (multiples of 8: no padding)
PROBE_SHAPE = (64, 256)
#: below this spread a logit or descriptor channel counts as constant across the probe's cells
_FLAT = 1e-6
#: no output of a working network on an image in [0, 1] comes near this
_HUGE = 1e6


@functools.cache
def probe_image() -> np.ndarray:
    """The probe: a deterministic uint8 intensity image of `PROBE_SHAPE`, blocks of random grey (corners and
    edges at several scales) over a ramp. Read-only."""
    rng = np.random.default_rng(20270527)
    h, w = PROBE_SHAPE
    fine = np.kron(rng.integers(0, 256, (h // 4, w // 4)), np.ones((4, 4)))
    coarse = np.kron(rng.integers(0, 256, (h // 16, w // 16)), np.ones((16, 16)))
    ramp = np.linspace(0, 255, w)[None, :]
    img = (0.4 * fine + 0.4 * coarse + 0.2 * ramp).round().astype(np.uint8)
    img.flags.writeable = False
    return img


def check_outputs(semi: np.ndarray, desc: np.ndarray, arch: SuperPointArch, model: str) -> None:
    """`ArtifactError` naming ``model`` unless the network's outputs on `probe_image`, (65, H/8, W/8) logits
    ``semi`` and (D, H/8, W/8) descriptors ``desc``, are what a working network of ``arch`` gives."""
    h, w = PROBE_SHAPE
    cells = (h // CELL, w // CELL)
    fix = "the model is not a working SuperPoint network of its weights' architecture and is not run"
    semi, desc = np.asarray(semi), np.asarray(desc)
    if semi.shape != (DETECTOR_CHANNELS, *cells):
        raise ArtifactError(
            f"{model}: on a {h} x {w} probe image the detector gives logits of shape {semi.shape}, not "
            f"{(DETECTOR_CHANNELS, *cells)}; {fix}"
        )
    if desc.shape != (arch.descriptor_dim, *cells):
        got = f"{desc.shape[0]}-d descriptors" if desc.ndim == 3 and desc.shape[1:] == cells else desc.shape
        raise ArtifactError(
            f"{model}: on a {h} x {w} probe image it gives {got}, but its weights' architecture says "
            f"{arch.descriptor_dim}-d descriptors of shape {(arch.descriptor_dim, *cells)} (vocabularies and "
            f"databases are built for the architecture's size); {fix}"
        )
    for name, out in (("detector logits", semi), ("descriptors", desc)):
        # cv2.dnn's ReLU turns a NaN into a huge finite number: a NaN bias shows as |x| ~ 1e37
        bad = int(np.count_nonzero(~(np.abs(out) <= _HUGE)))
        if bad:
            raise ArtifactError(
                f"{model}: {bad} of its {out.size} {name} on the probe image are not finite, or beyond "
                f"+-{_HUGE:g} (a NaN or overflow inside the network); {fix}"
            )
    if float(np.ptp(semi.reshape(len(semi), -1), axis=1).max()) <= _FLAT:
        raise ArtifactError(
            f"{model}: its detector logits are the same in every cell of the probe image; {fix}"
        )
    d = desc.reshape(len(desc), -1).astype(np.float64)
    norm = np.linalg.norm(d, axis=0)
    live = norm > _FLAT
    if not live.any():
        raise ArtifactError(f"{model}: its descriptors on the probe image are all zero; {fix}")
    unit = d[:, live] / norm[live]
    if live.sum() < 2 or float(np.ptp(unit, axis=1).max()) <= _FLAT:
        raise ArtifactError(f"{model}: its descriptors are the same in every cell of the probe image; {fix}")
