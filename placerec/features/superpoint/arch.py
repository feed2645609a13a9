"""The SuperPoint network's layout (DeTone et al., 2018), described once for torch, ONNX and the weights file.

A VGG-style encoder of four stages of two 3x3 convolutions + ReLU, the first three followed by 2x2 max pooling
(so cells are 8x8 pixels), then two heads on the shared features:

* detector: 3x3 conv + ReLU, then 1x1 conv to 65 channels (64 positions of the cell + a "no keypoint" dustbin);
  softmax over the 65, the dustbin dropped, depth-to-space gives a full-resolution keypoint probability;
* descriptor: 3x3 conv + ReLU, then 1x1 conv to ``descriptor_dim``; sampled bicubically at each keypoint and
  L2-normalised.

The paper's widths are ``encoder=(64, 64, 128, 128)``, ``head=256``, 256-d descriptors. Our default is narrower
(see `SuperPointArch`): on two CPU cores the paper's encoder takes about four times as long per 64 x 1024 image,
and the narrow one meets the 30 ms target through ``cv2.dnn`` (``tools/eval_features.py``).

Every layer is a `Conv` with a stable name; its weights are ``<name>.weight`` (out, in, k, k) and ``<name>.bias``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from placerec.params import Params

__all__ = ["SuperPointArch", "Conv", "conv_layers", "network_input", "CELL", "DETECTOR_CHANNELS"]

#: pixels per cell side (three 2x2 poolings)
CELL = 8
#: 64 positions of an 8x8 cell + the dustbin
DETECTOR_CHANNELS = CELL * CELL + 1


class SuperPointArch(Params):
    """Widths of the SuperPoint network (the paper's: encoder (64, 64, 128, 128), head 256, descriptor 256)."""

    encoder: list[int] = Field(
        default_factory=lambda: [16, 32, 64, 128],
        min_length=4,
        max_length=4,
        description="channels of the four encoder stages (paper: 64, 64, 128, 128)",
    )
    head: int = Field(128, gt=0, description="channels of the heads' 3x3 convolutions (paper: 256)")
    descriptor_dim: int = Field(256, gt=0, description="descriptor dimension (paper: 256)")


@dataclass(frozen=True)
class Conv:
    """One convolution (+ ReLU unless it ends a head); ``pool_after`` adds a 2x2 max pooling after the ReLU."""

    name: str
    c_in: int
    c_out: int
    kernel: int
    relu: bool = True
    pool_after: bool = False


def conv_layers(arch: SuperPointArch) -> tuple[list[Conv], list[Conv], list[Conv]]:
    """(encoder, detector head, descriptor head) layers of ``arch``, in order."""
    encoder: list[Conv] = []
    c_in = 1
    for stage, width in enumerate(arch.encoder, start=1):
        encoder.append(Conv(f"conv{stage}a", c_in, width, 3))
        encoder.append(Conv(f"conv{stage}b", width, width, 3, pool_after=stage < 4))
        c_in = width
    detector = [
        Conv("convPa", c_in, arch.head, 3),
        Conv("convPb", arch.head, DETECTOR_CHANNELS, 1, relu=False),
    ]
    descriptor = [
        Conv("convDa", c_in, arch.head, 3),
        Conv("convDb", arch.head, arch.descriptor_dim, 1, relu=False),
    ]
    return encoder, detector, descriptor


def network_input(image: np.ndarray) -> np.ndarray:
    """The network's (1, 1, H, W) float input of a uint8 intensity image (what every backend and the int8
    calibration feed it)."""
    return (np.asarray(image, np.float32) / 255.0)[None, None]
