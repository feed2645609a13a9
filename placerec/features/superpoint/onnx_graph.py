"""The SuperPoint network as an ONNX graph, written from the weights with ``onnx.helper`` (no torch needed).

OpenCV's ``cv2.dnn`` runs it, so SuperPoint works where torch is not installed. Inputs ``image`` (1, 1, H, W)
float32 in [0, 1] (H and W multiples of 8); outputs ``semi`` (1, 65, H/8, W/8) and ``desc`` (1, D, H/8, W/8),
exactly the torch model's (`placerec.features.superpoint.torch_model`).
"""

from __future__ import annotations

import numpy as np

from placerec.errors import DependencyError
from placerec.features.superpoint.arch import DETECTOR_CHANNELS, Conv, SuperPointArch, conv_layers

__all__ = ["onnx_model_bytes"]

#: ONNX opset of the written graph (Conv, Relu, MaxPool only; cv2.dnn reads it)
OPSET = 13


def onnx_model_bytes(arch: SuperPointArch, weights: dict[str, np.ndarray]) -> bytes:
    """The serialised ONNX model of ``arch`` with ``weights`` (float32 initialisers)."""
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ImportError as exc:
        raise DependencyError("writing SuperPoint's ONNX model needs onnx (pip install onnx)") from exc
    enc, det, desc = conv_layers(arch)
    nodes, inits = [], []

    def chain(layers: list[Conv], x: str, out: str) -> str:
        for i, c in enumerate(layers):
            w, b = f"{c.name}.weight", f"{c.name}.bias"
            inits.append(numpy_helper.from_array(np.asarray(weights[w], np.float32), w))
            inits.append(numpy_helper.from_array(np.asarray(weights[b], np.float32), b))
            last = i == len(layers) - 1 and not c.relu
            y = out if last else c.name
            p = c.kernel // 2
            nodes.append(helper.make_node("Conv", [x, w, b], [y], kernel_shape=[c.kernel] * 2, pads=[p] * 4))
            x = y
            if c.relu:
                nodes.append(helper.make_node("Relu", [x], [f"{c.name}.relu"]))
                x = f"{c.name}.relu"
            if c.pool_after:
                nodes.append(
                    helper.make_node("MaxPool", [x], [f"{c.name}.pool"], kernel_shape=[2, 2], strides=[2, 2])
                )
                x = f"{c.name}.pool"
        return x

    feat = chain(enc, "image", "")
    chain(det, feat, "semi")
    chain(desc, feat, "desc")
    graph = helper.make_graph(
        nodes,
        "superpoint",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 1, "H", "W"])],
        [
            helper.make_tensor_value_info("semi", TensorProto.FLOAT, [1, DETECTOR_CHANNELS, "h", "w"]),
            helper.make_tensor_value_info("desc", TensorProto.FLOAT, [1, arch.descriptor_dim, "h", "w"]),
        ],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="placerec")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model.SerializeToString()
