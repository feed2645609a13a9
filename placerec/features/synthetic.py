"""A deterministic synthetic texture for feature tests and benchmarks (no image files needed)."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["textured_image"]


def textured_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Deterministic 'real-ish' texture in [20, 215]: multi-scale smoothed noise, filled rectangles and ellipses,
    letters drawn with cv2 (so +40 gray levels never saturate)."""
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 128.0, np.float32)
    for sigma, amp in ((6.0, 70.0), (2.5, 50.0), (1.0, 25.0)):
        n = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
        img += amp * n / (n.std() + 1e-9)
    img = (np.clip(img, 0, 255) * (195 / 255) + 20).astype(np.uint8)
    for _ in range(h * w // 900):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        a, b = int(rng.integers(3, 20)), int(rng.integers(3, 20))
        col = int(rng.integers(20, 216))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + a, y + b), col, -1)
        else:
            cv2.ellipse(img, (x, y), (a // 2 + 1, b // 2 + 1), float(rng.integers(0, 180)), 0, 360, col, -1)
    for _ in range(h * w // 1500):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        letter = chr(int(rng.integers(65, 91)))
        scale = float(rng.uniform(0.4, 1.3))
        cv2.putText(img, letter, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, int(rng.integers(20, 216)), 2)
    return img
