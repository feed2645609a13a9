"""SuperPoint's weights (kind ``superpoint-weights``): SuperPoint trained on simulated LiDAR intensity images with
correspondences from known poses (needs torch).

The pairs, the ground-truth correspondences and the detector labels are made by
`placerec.experiment.superpoint_pairs` (repeatability of 3D points across views). Here:

* **Detector loss**: SuperPoint's cross-entropy over the 65 channels of every 8x8 cell.
* **Descriptor loss: InfoNCE** on ``samples`` correspondences per pair (both directions, temperature ``tau``),
  descriptors sampled bicubically from the coarse map as at inference; correspondences closer than
  ``negative_px`` to the positive are not used as its negatives.
* **Augmentation**: photometric (gain, gamma, Gaussian noise), azimuth shift and crop: image A is cropped to
  ``crop_width`` columns at a random azimuth, image B around where A's crop lands in it (from the
  correspondences), with a random jitter; both wrap around the panorama.
* Adam with a cosine-decayed learning rate, fixed seeds, a validation set of pairs from a held-out world seed.

`train_superpoint` writes the weights (float16 ``.npz`` + ``.onnx``), the provenance ``.json`` beside them (with
both files' sha256, which the extractor checks before it runs them: docs/superpoint.md) and the loss curves (``curves``/loss_curves.json and .png), and returns the provenance; `build_superpoint_weights` is the
same as a builder, returning the weights' path.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from placerec._version import __version__
from placerec.config import load_params_file
from placerec.experiment.superpoint_pairs import (
    PairData,
    TrainingData,
    build_pairs,
    cell_labels,
    data_fingerprint,
)
from placerec.features.superpoint.arch import CELL, SuperPointArch
from placerec.features.superpoint.torch_model import build_torch_model, import_torch, model_weights
from placerec.features.superpoint.weights import provenance_path, save_weights
from placerec.io.atomic import atomic_write
from placerec.params import Params

log = logging.getLogger(__name__)

__all__ = [
    "TrainingSchedule",
    "SuperPointTrainingConfig",
    "load_superpoint_config",
    "make_batch",
    "train_superpoint",
    "build_superpoint_weights",
]


class TrainingSchedule(Params):
    """Optimisation and augmentation."""

    steps: int = Field(2500, ge=1)
    batch: int = Field(8, ge=1, description="pairs per step")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate")
    lr_final: float = Field(1e-4, gt=0, description="cosine-decayed to this")
    crop_width: int = Field(256, gt=0, description="px, a multiple of 8")
    shift_jitter: int = Field(16, ge=0, description="px of random offset between the two crops")
    samples: int = Field(256, gt=1, description="correspondences per pair for the descriptor loss")
    tau: float = Field(0.1, gt=0, description="InfoNCE temperature")
    negative_px: float = Field(8.0, ge=0, description="px; nearer correspondences are not negatives")
    descriptor_weight: float = Field(1.0, ge=0)
    gain: list[float] = Field(default_factory=lambda: [0.7, 1.3], min_length=2, max_length=2)
    gamma: list[float] = Field(default_factory=lambda: [0.8, 1.25], min_length=2, max_length=2)
    noise: float = Field(0.02, ge=0, description="std of additive noise (image in [0, 1])")
    validate_every: int = Field(250, ge=1)
    log_every: int = Field(25, ge=1)
    threads: int = Field(2, ge=1, description="torch CPU threads")
    seed: int = 0


class SuperPointTrainingConfig(Params):
    """``configs/superpoint.yaml``: architecture, data, schedule, outputs."""

    arch: SuperPointArch = Field(default_factory=SuperPointArch)
    data: TrainingData = Field(default_factory=TrainingData)
    train: TrainingSchedule = Field(default_factory=TrainingSchedule)
    cache: str = Field(".cache/superpoint", description="folder caching the rendered training pairs")
    output: str = Field("placerec/vocab/superpoint_lidar.npz", description="weights (+ .onnx, .json beside)")
    curves: str = Field("results/superpoint", description="folder for the loss curves (json, png)")


def load_superpoint_config(path: str | Path | None, **overrides: Any) -> SuperPointTrainingConfig:
    """A training config from YAML (None: defaults) with top-level overrides; `ConfigError` on bad keys."""
    return load_params_file(SuperPointTrainingConfig, path, "superpoint training config", **overrides)


# ----------------------------------------------------------------------------- batches


def _crop_columns(start: int, width: int, total: int) -> np.ndarray:
    return (start + np.arange(width)) % total


def _inside(u: np.ndarray, start: int, width: int, total: int) -> tuple[np.ndarray, np.ndarray]:
    """Mask of columns ``u`` inside the wrapped crop [start, start + width), and their crop column."""
    c = (u.astype(np.int64) - start) % total
    return c < width, c


def _photometric(img: np.ndarray, s: TrainingSchedule, rng: np.random.Generator) -> np.ndarray:
    x = img.astype(np.float32) / 255.0
    x = rng.uniform(s.gain[0], s.gain[1]) * np.power(x, rng.uniform(s.gamma[0], s.gamma[1]))
    x = x + rng.normal(0.0, s.noise, x.shape).astype(np.float32)
    return np.clip(x, 0.0, 1.0)


def make_batch(
    pairs: list[PairData], s: TrainingSchedule, rng: np.random.Generator, augment: bool = True
) -> dict:
    """Stacked crops (B, 1, 64, crop) of both images, their cell labels (B, 8, crop/8), sampled correspondences
    (B, samples, 2) in crop pixels (u, v) for A and B."""
    cw = s.crop_width
    xs: dict[str, list] = {k: [] for k in ("xa", "xb", "la", "lb", "ca", "cb")}
    for p in pairs:
        wa, wb = p.image_a.shape[1], p.image_b.shape[1]
        for _ in range(20):  # a crop of A with enough correspondences
            sa = int(rng.integers(wa)) if augment else 0
            ok, col_a = _inside(p.uv_a[:, 0], sa, cw, wa)
            if ok.sum() >= 16:
                break
        shift = np.angle(np.mean(np.exp(2j * np.pi * (p.uv_b[ok, 0] - col_a[ok]) / wb)))
        sb = int(round(shift / (2 * np.pi) * wb)) + (
            int(rng.integers(-s.shift_jitter, s.shift_jitter + 1)) if augment else 0
        )
        sb %= wb
        ok_b, col_b = _inside(p.uv_b[:, 0], sb, cw, wb)
        both = np.flatnonzero(ok & ok_b)
        pick = rng.choice(both, s.samples, replace=len(both) < s.samples) if len(both) else np.zeros(0, int)
        ca = np.stack([col_a[pick], p.uv_a[pick, 1]], axis=1)
        cb = np.stack([col_b[pick], p.uv_b[pick, 1]], axis=1)
        if len(pick) == 0:  # no overlap: a pair with no descriptor term (its weight is 0 below)
            ca = cb = np.full((s.samples, 2), -1, np.int64)
        img_a = p.image_a[:, _crop_columns(sa, cw, wa)]
        img_b = p.image_b[:, _crop_columns(sb, cw, wb)]
        for img, kp, resp, start, total, key in (
            (img_a, p.kp_a, p.resp_a, sa, wa, "a"),
            (img_b, p.kp_b, p.resp_b, sb, wb, "b"),
        ):
            m, c = _inside(kp[:, 0], start, cw, total)
            uv = np.stack([c[m], kp[m, 1].astype(np.int64)], axis=1)
            xs["l" + key].append(cell_labels(uv, resp[m], img.shape[0], cw))
            xs["x" + key].append(_photometric(img, s, rng) if augment else img.astype(np.float32) / 255.0)
        xs["ca"].append(ca)
        xs["cb"].append(cb)
    return {k: np.stack(v) for k, v in xs.items()}


# ----------------------------------------------------------------------------- losses


def _sample(torch: Any, desc: Any, uv: Any, height: int, width: int) -> Any:
    """(B, N, D) unit descriptors at pixels ``uv`` (B, N, 2): bicubic, border padding (as inference)."""
    grid = torch.stack([(uv[..., 0] + 0.5) / width * 2 - 1, (uv[..., 1] + 0.5) / height * 2 - 1], dim=-1)
    d = torch.nn.functional.grid_sample(
        desc, grid[:, None].float(), mode="bicubic", padding_mode="border", align_corners=False
    )[:, :, 0]
    return torch.nn.functional.normalize(d.transpose(1, 2), dim=-1)


def _losses(torch: Any, model: Any, batch: dict, s: TrainingSchedule) -> tuple[Any, Any, Any]:
    """(detector loss, descriptor loss, descriptor top-1 accuracy) of a batch."""
    F = torch.nn.functional
    x = torch.from_numpy(np.concatenate([batch["xa"], batch["xb"]]))[:, None]
    labels = torch.from_numpy(np.concatenate([batch["la"], batch["lb"]]))
    semi, desc = model(x)
    det = F.cross_entropy(semi, labels)
    n = batch["xa"].shape[0]
    h, w = x.shape[2:]
    ca, cb = torch.from_numpy(batch["ca"]), torch.from_numpy(batch["cb"])
    da, db = _sample(torch, desc[:n], ca, h, w), _sample(torch, desc[n:], cb, h, w)
    sim = da @ db.transpose(1, 2) / s.tau  # (B, N, N)
    near_b = torch.cdist(cb.float(), cb.float()) < s.negative_px
    near_a = torch.cdist(ca.float(), ca.float()) < s.negative_px
    eye = torch.eye(sim.shape[1], dtype=torch.bool)[None]
    target = torch.arange(sim.shape[1]).expand(sim.shape[0], -1)
    valid = (ca[:, 0, 0] >= 0).float()
    l_ab = F.cross_entropy(sim.masked_fill(near_b & ~eye, -1e4).transpose(1, 2), target, reduction="none")
    l_ba = F.cross_entropy(sim.masked_fill(near_a & ~eye, -1e4), target, reduction="none")
    per_pair = 0.5 * (l_ab.mean(1) + l_ba.mean(1))
    descriptor = (per_pair * valid).sum() / valid.sum().clamp(min=1)
    acc = ((sim.argmax(2) == target).float().mean(1) * valid).sum() / valid.sum().clamp(min=1)
    return det, descriptor, acc


# ----------------------------------------------------------------------------- training


def train_superpoint(cfg: SuperPointTrainingConfig, progress: bool = False) -> dict[str, Any]:
    """Train, then write the weights, provenance and loss curves (see the module docstring); returns the
    provenance as written (with the files' ``sha256``)."""

    torch = import_torch()
    s = cfg.train
    if s.crop_width % CELL:
        raise ValueError(f"train.crop_width must be a multiple of {CELL}, got {s.crop_width}")
    torch.set_num_threads(s.threads)
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)

    t0 = time.perf_counter()
    pairs = build_pairs(cfg.data, cfg.cache, progress)
    data_s = time.perf_counter() - t0
    train, val = pairs["train"], pairs["validation"]
    log.info("%d training pairs, %d validation pairs (%.0f s)", len(train), len(val), data_s)
    val_rng = np.random.default_rng(12345)
    val_batches = [
        make_batch(val[k : k + s.batch], s, val_rng, augment=False) for k in range(0, len(val), s.batch)
    ]

    model = build_torch_model(cfg.arch)
    opt = torch.optim.Adam(model.parameters(), lr=s.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, s.steps, eta_min=s.lr_final)
    curves: dict[str, list] = {
        "step": [],
        "detector": [],
        "descriptor": [],
        "accuracy": [],
        "val_step": [],
        "val_detector": [],
        "val_descriptor": [],
        "val_accuracy": [],
    }
    window: list[tuple[float, float, float]] = []
    t1 = time.perf_counter()
    steps = range(1, s.steps + 1)
    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress()
        bar.start()
        task = bar.add_task("training SuperPoint", total=s.steps)
    try:
        for step in steps:
            model.train()
            batch = make_batch([train[i] for i in rng.choice(len(train), s.batch, replace=False)], s, rng)
            det, desc, acc = _losses(torch, model, batch, s)
            loss = det + s.descriptor_weight * desc
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            window.append((det.item(), desc.item(), acc.item()))
            if step % s.log_every == 0 or step == s.steps:
                m = np.mean(window, axis=0)
                window.clear()
                for k, v in zip(("detector", "descriptor", "accuracy"), m, strict=True):
                    curves[k].append(round(float(v), 5))
                curves["step"].append(step)
            if step % s.validate_every == 0 or step == s.steps:
                model.eval()
                with torch.no_grad():
                    v = np.mean(
                        [[float(t) for t in _losses(torch, model, b, s)] for b in val_batches], axis=0
                    )
                for k, x in zip(("val_detector", "val_descriptor", "val_accuracy"), v, strict=True):
                    curves[k].append(round(float(x), 5))
                curves["val_step"].append(step)
                log.info("step %d: val detector %.3f descriptor %.3f top-1 %.3f", step, *v)
            if bar is not None:
                bar.update(task, advance=1)
    finally:
        if bar is not None:
            bar.stop()
    train_s = time.perf_counter() - t1

    provenance = {
        "format_version": 1,
        "what": "SuperPoint trained on simulated LiDAR intensity images (placerec tools/train_superpoint.py)",
        "config": cfg.model_dump(mode="json"),
        "data_fingerprint": data_fingerprint(cfg.data),
        "pairs": {"train": len(train), "validation": len(val)},
        "data_seconds": round(data_s, 1),
        "train_seconds": round(train_s, 1),
        "torch": torch.__version__,
        "threads": s.threads,
        "final": {k: curves[k][-1] for k in curves if curves[k] and k not in ("step", "val_step")},
    }
    provenance["placerec_version"] = __version__
    # the .json beside the weights: this provenance with the sha256 of the .npz and .onnx (record_hashes)
    save_weights(cfg.output, cfg.arch, model_weights(model), {"provenance": provenance}, provenance)
    written = json.loads(provenance_path(cfg.output).read_text())
    _write_curves(Path(cfg.curves), curves)
    return written


def build_superpoint_weights(config: SuperPointTrainingConfig, progress: bool = False) -> Path:
    """`train_superpoint`; returns the path of the weights."""
    train_superpoint(config, progress)
    return Path(config.output)


def _write_curves(folder: Path, curves: dict[str, list]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_write(folder / "loss_curves.json", "w") as fh:
        json.dump(curves, fh)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, key, title in zip(
        axes,
        ("detector", "descriptor", "accuracy"),
        ("detector cross-entropy", "descriptor InfoNCE", "descriptor top-1 in batch"),
        strict=True,
    ):
        ax.plot(curves["step"], curves[key], label="train", lw=1)
        ax.plot(curves["val_step"], curves["val_" + key], "o-", label="validation", ms=3)
        ax.set_title(title)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(folder / "loss_curves.png", dpi=110)
    plt.close(fig)
