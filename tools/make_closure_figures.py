"""The docs' figures that show a loop closure, drawn by the report's evidence renderer
(`placerec.experiment.evidence_figures.draw_pair`): the query's and the match's intensity images with the keypoint
pairs verification was given (inliers green, the rest faint red), the bird's-eye overlay after ICP and the
verification's numbers.

* ``docs/figures/closure_os1_64_real_pair.png`` — the real OS1-64 revisit pair (MulRan, organised 64 x 1024),
  verified by orb-hbst (docs/intensity_images.md); needs ``../shared/data/real``;
* ``docs/figures/closure_sim_revisit_same.png``, ``closure_sim_revisit_opposite.png`` — the simulated town's longest same- and opposite-direction revisits
  of configs/demo.yaml's route (OS1-64, seed 0, preprocessed as the demo does), each query verified by orb-hbst
  against the nearest scan of the first visit, with the pose error against the simulator's poses
  (docs/simulator.md).

    .venv/bin/python tools/make_closure_figures.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from placerec.config import load_config  # noqa: E402
from placerec.experiment.datasets import open_dataset  # noqa: E402
from placerec.experiment.evidence_figures import draw_pair  # noqa: E402
from placerec.experiment.preprocessing import preprocessed_scan  # noqa: E402
from placerec.io import read_scan  # noqa: E402
from placerec.recognizer import PIPELINES, make_pipeline  # noqa: E402
from placerec.sim import SimulatedSequence  # noqa: E402
from placerec.types import Candidate, PlaceRecognizer, Scan, relative_pose  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "real"
OUT = ROOT / "docs" / "figures"
PIPELINE = "orb-hbst"


def _verified(rec: PlaceRecognizer, query: Scan, match: Scan) -> Candidate | None:
    """``rec``'s best candidate for ``query`` with ``match`` (id 0) as its only database entry (None: none)."""
    rec.add_description(0, rec.describe(match))
    cands = rec.query_description(rec.describe(query), k=1, query_id=1)
    return cands[0] if cands else None


def _draw(
    rec: PlaceRecognizer, query: Scan, match: Scan, path: Path, truth: np.ndarray | None, ids: tuple[int, int]
) -> None:
    cand = _verified(rec, query, match)
    threshold = PIPELINES[PIPELINE].threshold
    assert threshold is not None  # orb-hbst's preset has its operating threshold
    kind = "accepted" if cand is not None and cand.accepted else "missed"
    view = draw_pair(PIPELINE, kind, query, match, cand, rec, path, threshold, True, truth, ids)
    print(f"wrote {path.relative_to(ROOT)}: {view.title}")


def real_pair() -> None:
    layout = (64, 1024, "column-major")
    pair = REAL / "ouster_os1_64_revisit_pair"
    a = read_scan(pair / "32line_1.bin", organized=True, layout=layout)
    b = read_scan(pair / "32line_2.bin", organized=True, layout=layout)
    _draw(make_pipeline(PIPELINE), b, a, OUT / "closure_os1_64_real_pair.png", None, (2, 1))


def sim_revisits() -> None:
    cfg = load_config(ROOT / "configs" / "demo.yaml")
    seq = open_dataset(cfg.dataset)
    assert isinstance(seq, SimulatedSequence) and seq.poses is not None
    xy = seq.poses[:, :2, 3]
    for kind in ("same", "opposite"):
        r = max((x for x in seq.revisits if x.kind == kind), key=lambda x: x.stop - x.start)
        i = (r.start + r.stop) // 2
        j = r.ref_start + int(np.argmin(np.linalg.norm(xy[r.ref_start : r.ref_stop] - xy[i], axis=1)))
        truth = relative_pose(seq.poses[j], seq.poses[i])
        query, match = (preprocessed_scan(seq, k, cfg.preprocess)[0] for k in (i, j))
        _draw(make_pipeline(PIPELINE), query, match, OUT / f"closure_sim_revisit_{kind}.png", truth, (i, j))


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    sim_revisits()
    if REAL.is_dir():
        real_pair()
    else:
        print(f"skipping the real pair: {REAL} not found")


if __name__ == "__main__":
    main()
