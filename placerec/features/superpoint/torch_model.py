"""The SuperPoint network in torch (an optional dependency: ``pip install placerec[superpoint]``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from placerec.errors import DependencyError
from placerec.features.superpoint.arch import Conv, SuperPointArch, conv_layers

__all__ = ["import_torch", "build_torch_model", "model_weights"]


def import_torch() -> Any:
    """The ``torch`` module, or `DependencyError` saying how to install it."""
    try:
        import torch
    except ImportError as exc:
        raise DependencyError(
            "SuperPoint's torch backend needs torch (pip install 'placerec[superpoint]', a CPU build: "
            "torch==2.13.0); the cv2 backend runs the shipped ONNX model without it"
        ) from exc
    return torch


def build_torch_model(arch: SuperPointArch, weights: dict[str, np.ndarray] | None = None) -> Any:
    """A ``torch.nn.Module`` mapping (B, 1, H, W) images in [0, 1] to ``(semi, coarse_desc)``: (B, 65, H/8, W/8)
    detector logits and (B, D, H/8, W/8) descriptors (not normalised). ``weights``: ``{name: array}`` as in
    `placerec.features.superpoint.weights` (None: torch's default initialisation)."""
    torch = import_torch()
    nn = torch.nn

    def block(layers: list[Conv]) -> Any:
        mods: list[Any] = []
        for c in layers:
            conv = nn.Conv2d(c.c_in, c.c_out, c.kernel, padding=c.kernel // 2)
            mods.append(conv)
            if c.relu:
                mods.append(nn.ReLU(inplace=True))
            if c.pool_after:
                mods.append(nn.MaxPool2d(2, 2))
        return nn.Sequential(*mods)

    module: Any = nn.Module  # torch is imported here, so its classes are values to the type checker

    class SuperPointNet(module):
        def __init__(self) -> None:
            super().__init__()
            enc, det, desc = conv_layers(arch)
            self.layers = {c.name: c for c in enc + det + desc}
            self.encoder, self.detector, self.descriptor = block(enc), block(det), block(desc)

        def named_convs(self) -> dict[str, Any]:
            convs = [
                m
                for seq in (self.encoder, self.detector, self.descriptor)
                for m in seq
                if isinstance(m, nn.Conv2d)
            ]
            return dict(zip(self.layers, convs, strict=True))

        def forward(self, x: Any) -> tuple[Any, Any]:
            f = self.encoder(x)
            return self.detector(f), self.descriptor(f)

    model = SuperPointNet()
    if weights is not None:
        with torch.no_grad():
            for name, conv in model.named_convs().items():
                conv.weight.copy_(torch.from_numpy(np.asarray(weights[f"{name}.weight"], np.float32)))
                conv.bias.copy_(torch.from_numpy(np.asarray(weights[f"{name}.bias"], np.float32)))
    return model


def model_weights(model: Any) -> dict[str, np.ndarray]:
    """``{name.weight / name.bias: float32 array}`` of a model from `build_torch_model`."""
    out: dict[str, np.ndarray] = {}
    for name, conv in model.named_convs().items():
        out[f"{name}.weight"] = conv.weight.detach().cpu().numpy().astype(np.float32)
        out[f"{name}.bias"] = conv.bias.detach().cpu().numpy().astype(np.float32)
    return out
