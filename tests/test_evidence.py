"""The report's per-closure evidence: which closures the galleries show, why candidates were rejected, the lines
and overlays of a closure figure, and a real run's page (every file it references exists)."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from placerec.errors import ScanDataError
from placerec.eval import ExclusionWindow, evaluate_loop
from placerec.experiment.evidence import (
    UNVERIFIED,
    decision_text,
    rejection_counts,
    select_cases,
    spread,
)
from placerec.experiment.evidence_figures import bev_raster, correspondence_segments
from placerec.experiment.runner import PipelineRecord
from placerec.types import Candidate, Verification, relative_pose
from tests.test_run_sim import TINY as TINY_RUN


def _pose(x, y, yaw_deg=0.0):
    T = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def _verification(accepted, rejection=None, T=None):
    return Verification(
        np.eye(4) if T is None else T,
        0.9 if accepted else 0.0,
        accepted,
        20 if accepted else 2,
        40,
        0.8 if accepted else float("nan"),
        0.2 if accepted else float("nan"),
        0.01 if accepted else float("nan"),
        rejection=rejection,
    )


def _cand(q, m, score, accepted, rejection=None, T=None):
    return Candidate(q, m, score, T, accepted=accepted, verification=_verification(accepted, rejection, T))


# scans 0-9 on y = 0 (10 m apart), 10-19 far away (y = 500), 20-24 revisit 0-4 (0.5 m off): the revisits are
# exactly queries 20-24, query k's true match scan k - 20
POSES = np.stack(
    [_pose(10 * i, 0) for i in range(10)]
    + [_pose(10 * i, 500) for i in range(10)]
    + [_pose(10 * i, 0.5, 3.0) for i in range(5)]
)
#: the estimate of query 20's closure: the truth moved 0.3 m along x and turned 2 degrees
EST_20 = relative_pose(POSES[0], POSES[20]) @ _pose(0.3, 0.0, 2.0)


@pytest.fixture(scope="module")
def constructed():
    """A record with one case of each outcome at the max-F1 threshold (0.9: query 20's true closure):
    20 accepted true (score 0.9), 21 accepted false (0.95, the wrong place 15), 22 missed (top wrong and rejected
    by RANSAC, the right place 2 second and rejected by fitness), 23 missed with no candidate, 24 missed below the
    threshold (the right place, accepted by verification, score 0.1); queries 10-19 (no revisits) close wrongly
    at 0.5."""
    cands: dict[int, list[Candidate]] = {q: [] for q in range(len(POSES))}
    for q in range(10, 20):
        cands[q] = [_cand(q, 0, 0.5, True)]
    cands[20] = [_cand(20, 0, 0.9, True, T=EST_20)]
    cands[21] = [_cand(21, 15, 0.95, True)]
    cands[22] = [_cand(22, 16, 0.0, False, "ransac"), _cand(22, 2, 0.0, False, "fitness")]
    cands[24] = [_cand(24, 4, 0.1, True)]
    record = PipelineRecord("p", "P", "p", query_ids=list(cands), candidates=list(cands.values()))
    q, m, s = record.table().top1()
    metrics, gt = evaluate_loop(q, m, s, POSES, exclusion=ExclusionWindow(frames=5))
    assert metrics.threshold_at_max_f1 == pytest.approx(0.9)
    assert np.flatnonzero(metrics.revisit).tolist() == [20, 21, 22, 23, 24]
    return record, metrics, gt


def test_each_gallery_holds_the_right_closures(constructed):
    record, metrics, gt = constructed
    cases = select_cases(record, metrics, gt, POSES, per_gallery=5)
    got = [(c.kind, c.query_id, c.match_id, c.rank, c.correct) for c in cases]
    assert got == [
        ("accepted", 20, 0, 0, True),
        ("false", 21, 15, 0, False),
        ("missed", 22, 2, 1, True),  # the right place, second and rejected, not the wrong top one
        ("missed", 23, 3, -1, True),  # no candidate: the scan it revisits
        ("missed", 24, 4, 0, True),
    ]
    decisions = {c.query_id: c.decision for c in cases}
    assert decisions[20] == "accepted"
    assert decisions[21] == "accepted"
    assert decisions[22] == "rejected: ICP overlap (fitness) below min_fitness"
    assert decisions[23] == "no candidate"
    assert decisions[24] == "below threshold (0.1 < 0.9)"
    assert cases[3].candidate is None and cases[3].T_match_query is None


def test_the_pose_error_is_that_of_the_estimate_against_the_truth(constructed):
    record, metrics, gt = constructed
    accepted = select_cases(record, metrics, gt, POSES, per_gallery=5)[0]
    assert accepted.translation_m == pytest.approx(0.3, abs=1e-9)
    assert accepted.rotation_deg == pytest.approx(2.0, abs=1e-9)
    assert accepted.distance_m == pytest.approx(0.5)  # query 20 is 0.5 m from scan 0
    # a candidate without a 6-DoF pose has no error (not the true offset)
    assert all(np.isnan(c.translation_m) for c in select_cases(record, metrics, gt, POSES, 5)[1:])


def test_a_gallery_is_bounded_and_spread_over_the_sequence(constructed):
    record, metrics, gt = constructed
    missed = [
        c.query_id for c in select_cases(record, metrics, gt, POSES, per_gallery=2) if c.kind == "missed"
    ]
    assert missed == [22, 24]
    assert spread(np.arange(100, 200), 4).tolist() == [100, 133, 166, 199]
    assert spread(np.array([3, 5]), 4).tolist() == [3, 5]


def test_the_rejection_counts(constructed):
    record, _, _ = constructed
    counts = rejection_counts(record.candidates)
    assert counts.all == {"accepted": 13, "ransac": 1, "fitness": 1}
    assert counts.top == {"accepted": 13, "ransac": 1}
    assert list(counts.as_dict()) == ["all", "top"]
    unverified = rejection_counts([[Candidate(1, 0, 0.4)], [Candidate(2, 0, 0.2), Candidate(2, 1, 0.1)], []])
    assert unverified.all == {UNVERIFIED: 3} and unverified.top == {UNVERIFIED: 2}


def test_a_pipeline_that_does_not_verify_is_judged_by_its_score():
    assert decision_text(Candidate(1, 0, 0.25), 0.5) == "below threshold (0.25 < 0.5)"
    assert decision_text(Candidate(1, 0, 0.75), 0.5) == "accepted"
    assert decision_text(None, 0.5) == "no candidate"


def test_the_lines_drawn_are_the_inlier_pairs():
    kq = np.array([[10, 1], [20, 2], [30, 3], [40, 4]], np.float32)
    km = np.array([[11, 5], [21, 6], [31, 7]], np.float32)
    matches = np.array([[0, 2], [1, 1], [3, 0], [2, 2]], np.int32)
    mask = np.array([True, False, True, True])
    inl, outl = correspondence_segments(matches, mask, kq, km, offset=100)
    assert len(inl) == mask.sum() and len(outl) == (~mask).sum()
    assert inl.tolist() == [
        [[10, 1], [31, 107]],
        [[40, 4], [11, 105]],
        [[30, 3], [31, 107]],
    ]
    assert outl.tolist() == [[[20, 2], [21, 106]]]
    with pytest.raises(ScanDataError, match="inlier mask of 3 for 4"):
        correspondence_segments(matches, mask[:3], kq, km, 100)
    with pytest.raises(ScanDataError, match="index 4 query and 3 match keypoints"):
        correspondence_segments(np.array([[0, 3]]), np.array([True]), kq, km, 100)


def test_the_overlay_marks_each_cloud_and_their_overlap():
    match = np.array([[10.1, 0.1, 0.0], [-5.1, 5.1, 1.0], [100.0, 0.0, 0.0]])  # the last: outside the view
    query = np.array([[10.2, 0.2, 0.0], [0.1, -20.1, 0.0]])
    rgb = bev_raster(match, query, radius=40.0, cell=1.0)
    assert rgb.shape == (80, 80, 3)
    colour = {tuple(c) for c in rgb.reshape(-1, 3)}
    assert len(colour) == 4  # white, match, query, both
    assert tuple(rgb[80 - 1 - 40, 50]) == (60, 60, 60)  # (10, 0): both clouds
    assert tuple(rgb[80 - 1 - 45, 34]) == (40, 90, 200)  # (-5, 5): the match's
    assert tuple(rgb[80 - 1 - 19, 40]) == (245, 130, 20)  # (0, -20): the query's
    assert (rgb == 255).all(axis=2).sum() == 80 * 80 - 3


#: the tiny run of tests/test_run_sim.py, 2 closures a gallery
TINY = TINY_RUN + "  evidence_per_gallery: 2\n"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny simulated run (the block loop twice) reported with its recognizers."""
    from placerec.config import load_config
    from placerec.experiment.report import report_loop
    from placerec.experiment.run_folder import make_run_dir
    from placerec.experiment.runner import build_pipelines, run_loop

    root = tmp_path_factory.mktemp("evidence")
    path = root / "tiny.yaml"
    path.write_text(TINY)
    cfg = load_config(path, [f"output.dir={root / 'results'}"])
    pipelines = build_pipelines(cfg)
    seq, records = run_loop(cfg, None, pipelines)
    run = make_run_dir(cfg)
    payload = report_loop(cfg, run, seq, records, recognizers=[rec for _, rec in pipelines])
    return run, payload, records


class _Refs(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.refs: list[tuple[str, str]] = []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in ("src", "href") and value:
                self.refs.append((tag, value))


def test_the_page_references_only_files_of_the_folder(tiny_run):
    run, _, _ = tiny_run
    parser = _Refs()
    parser.feed((run / "index.html").read_text())
    refs = [v for _, v in parser.refs]
    assert "plotly.min.js" in refs
    evidence = [v for v in refs if v.startswith("evidence/")]
    assert evidence and len(evidence) == len(list((run / "evidence").rglob("*.png")))
    for ref in refs:
        assert not re.match(r"[a-z]+://", ref), f"{ref}: the folder must open without a network"
        assert (run / ref).is_file(), ref


def test_the_run_shows_each_pipelines_evidence(tiny_run):
    run, payload, records = tiny_run
    page = (run / "index.html").read_text()
    on_disk = json.loads((run / "metrics.json").read_text())
    for record in records:
        label = record.label
        figures = sorted((run / "evidence" / label).glob("*.png"))
        kinds = [f.name.split("_")[0] for f in figures]
        assert 1 <= kinds.count("accepted") <= 2 and kinds.count("false") <= 2 and kinds.count("missed") <= 2
        assert f'id="evidence-{label}"' in page
        counts = rejection_counts(record.candidates).as_dict()
        assert (
            on_disk["pipelines"][label]["rejections"] == counts == payload["pipelines"][label]["rejections"]
        )
        assert sum(counts["top"].values()) == sum(1 for c in record.candidates if c)
    # the image-feature pipeline draws the pairs verification was given, green its inliers
    orb = records[[r.label for r in records].index("orb-hbst")]
    drawn = re.findall(r"query (\d+), match (\d+): accepted; (\d+) inlier pairs drawn of (\d+)", page)
    assert drawn
    for q, m, inliers, pairs in drawn:
        top = orb.candidates[orb.query_ids.index(int(q))][0]
        assert top.match_id == int(m)
        assert int(inliers) == top.verification.inliers == top.verification.inlier_mask.sum()
        assert int(pairs) == top.verification.correspondences == len(top.matches)
    assert "inlier pairs drawn" not in page.split('id="evidence-scan-context"')[1].split("</section>")[0]
    assert page.count('class="plotly-graph-div"') == 1 + len(records)  # PR curves + one trajectory each


def test_evidence_off_leaves_the_page_as_it_was(tmp_path):
    from placerec.config import load_config
    from placerec.experiment.report import report_loop
    from placerec.experiment.run_folder import make_run_dir
    from placerec.experiment.runner import run_loop
    from tests.test_experiment import pole_world_sequence

    cfg = load_config(
        None,
        [
            f"output.dir={tmp_path}",
            "output.cache_dir=null",
            "output.progress=false",
            "output.evidence=false",
            "evaluation.exclusion.frames=50",
            "pipelines=[{name: scan-context}]",
        ],
    )
    seq, records = run_loop(cfg, pole_world_sequence(n_loop=60, n_revisit=20))
    run = make_run_dir(cfg)
    payload = report_loop(cfg, run, seq, records)
    assert not (run / "evidence").exists() and not (run / "plotly.min.js").exists()
    assert "plotly" not in (run / "index.html").read_text()
    assert "rejections" in payload["pipelines"]["scan-context"]


def test_one_pair_outside_a_run_draws_its_verified_inliers(real_data, tmp_path):
    """`draw_pair` (the docs' closure figures) on the real OS1-64 revisit pair: the lines are the verification's
    pairs, its inliers green."""
    from placerec.experiment.evidence_figures import draw_pair
    from placerec.io import read_scan
    from placerec.recognizer import make_pipeline

    layout = (64, 1024, "column-major")
    pair = real_data / "ouster_os1_64_revisit_pair"
    a, b = (read_scan(pair / f"32line_{k}.bin", organized=True, layout=layout) for k in (1, 2))
    rec = make_pipeline("orb-hbst")
    rec.add_description(0, rec.describe(a))
    (cand,) = rec.query_description(rec.describe(b), k=1, query_id=1)
    view = draw_pair("orb-hbst", "accepted", b, a, cand, rec, tmp_path / "pair.png", 0.2, True, ids=(2, 1))
    assert (tmp_path / "pair.png").stat().st_size > 10_000
    assert len(view.inliers) == cand.verification.inliers == cand.verification.inlier_mask.sum()
    assert len(view.inliers) + len(view.outliers) == cand.verification.correspondences
    assert "query 2 (top) / match 1 (bottom): accepted" in view.title


def test_localize_galleries_show_answers_wrong_answers_and_the_best_unanswered_candidate(tmp_path):
    """Map scans 0-4 on y = 0, 10 m apart; queries 0-3 1 m off map scans 0-3: query 0 localised by map scan 0
    (its pose 0.5 m off), query 1 answered with map scan 4 (30 m from it), query 2 not answered (top: map scan 4
    rejected by RANSAC, then the right map scan 2 rejected by fitness), query 3 with no candidate."""
    from placerec.eval import localization_metrics
    from placerec.experiment.evidence import select_localize_cases
    from placerec.experiment.report import localize_estimates

    map_poses = np.stack([_pose(10 * i, 0) for i in range(5)])
    query_poses = np.stack([_pose(10 * i, 1.0) for i in range(4)])
    truth = lambda m, q: relative_pose(map_poses[m], query_poses[q])  # noqa: E731
    cands = [
        [_cand(0, 0, 0.9, True, T=truth(0, 0) @ _pose(0.5, 0))],
        [_cand(1, 4, 0.8, True, T=_pose(0.5, 0))],  # puts query 1 beside map scan 4: 30 m off
        [_cand(2, 4, 0.0, False, "ransac"), _cand(2, 2, 0.0, False, "fitness", T=truth(2, 2))],
        [],
    ]
    record = PipelineRecord("p", "P", "p", query_ids=[0, 1, 2, 3], candidates=cands)
    estimates, basis, rule = localize_estimates(record.table(), map_poses)
    metrics = localization_metrics(estimates, query_poses, 5.0, basis=basis, answer_rule=rule)
    cases = select_localize_cases(record, metrics, map_poses, query_poses, per_gallery=4)
    _localize_page_shows(record, map_poses, query_poses, tmp_path)
    got = [(c.kind, c.query_id, c.match_id, c.rank, c.correct, c.decision) for c in cases]
    assert got == [
        ("accepted", 0, 0, 0, True, "accepted"),
        ("false", 1, 4, 0, False, "accepted"),
        ("missed", 2, 2, 1, True, "rejected: ICP overlap (fitness) below min_fitness"),
        ("missed", 3, 3, -1, True, "no candidate"),
    ]
    assert cases[0].translation_m == pytest.approx(0.5)
    assert cases[2].translation_m == pytest.approx(0.0, abs=1e-9)  # the rejected candidate's pose was right


def _localize_page_shows(record, map_poses, query_poses, tmp_path):
    """``record`` reported in localize mode (the pole world's scans standing in for the map's and the queries'):
    one figure per gallery entry, the localize headings."""
    from placerec.config import load_config
    from placerec.experiment.report import report_localize
    from placerec.experiment.run_folder import make_run_dir
    from placerec.types import ListSequence
    from tests.test_experiment import pole_world_sequence

    scans = pole_world_sequence(n_loop=9, n_revisit=0)
    map_seq = ListSequence([scans[i] for i in range(5)], map_poses, name="map")
    query_seq = ListSequence([scans[i] for i in range(5, 9)], query_poses, name="queries")
    cfg = load_config(None, [f"output.dir={tmp_path}", "output.cache_dir=null", "evaluation.mode=localize"])
    run = make_run_dir(cfg)
    payload = report_localize(cfg, run, map_seq, query_seq, [record])
    names = sorted(p.name for p in (run / "evidence" / "p").glob("*.png"))
    assert names == [
        "accepted_000000_000000.png",
        "false_000001_000004.png",
        "missed_000002_000002.png",
        "missed_000003_000003.png",
    ]
    page = (run / "index.html").read_text()
    assert "Localised queries (the answer) (1 shown)" in page and "No answer" in page
    assert payload["pipelines"]["p"]["rejections"]["top"] == {"accepted": 2, "ransac": 1}


def test_the_interactive_trajectory_names_each_closure_and_why_a_revisit_was_missed(constructed):
    from placerec.experiment.interactive import trajectory_html

    record, metrics, _ = constructed
    html = trajectory_html(POSES[:, :3, 3], metrics, record.candidates, 0.9, "p", "trajectory-p")
    assert 'id="trajectory-p"' in html and "<script" in html and "cdn" not in html.lower()
    html = html.replace("\\u003c", "<").replace("\\u003e", ">")  # the figure's JSON escapes them
    for text in (
        "true closure (1)",
        "false closure (1)",
        "missed revisit (3)",
        "query 20 -> match 0",
        "query 21 -> match 15",
        "query 22: missed revisit<br>top candidate: match 16, score 0<br>rejected: too few RANSAC inliers",
        "query 23: missed revisit<br>no candidate",
        "query 24: missed revisit<br>top candidate: match 4, score 0.1<br>below threshold (0.1 < 0.9)",
    ):
        assert text in html, text


def test_the_run_exports_each_pipelines_closures_as_mcap(tiny_run):
    """closures_<label>.mcap holds each query's top candidate; the accepted edges are the report's closures at
    max F1 (true + false), the others say why they were not accepted."""
    from mcap.reader import make_reader

    from placerec.types import REJECTIONS

    run, payload, records = tiny_run
    for record in records:
        with (run / f"closures_{record.label}.mcap").open("rb") as fh:
            loops = [
                json.loads(msg.data)
                for _, ch, msg in make_reader(fh).iter_messages()
                if ch.topic == "/placerec/loop_closures"
            ]
        tops = {q: c[0] for q, c in zip(record.query_ids, record.candidates, strict=True) if c}
        assert [lp["query_index"] for lp in loops] == sorted(tops)
        for lp in loops:
            top = tops[lp["query_index"]]
            assert lp["match_index"] == top.match_id
            assert lp["accepted"] == (lp["rejection"] is None)
            if top.accepted is False:
                assert not lp["accepted"] and lp["rejection"] in REJECTIONS
        summary = payload["pipelines"][record.label]
        threshold = summary["threshold_at_max_f1"]
        n_accepted = sum(lp["accepted"] for lp in loops)
        expected = sum(1 for c in tops.values() if c.score >= threshold and c.accepted is not False)
        assert n_accepted == expected > 0


def test_figures_drawn_on_other_processes_are_the_same_files(tmp_path):
    """`plot_closures` on spawned processes writes the same PNG bytes as drawing in this process."""
    from placerec.experiment.evidence_figures import ClosureView, plot_closures

    rng = np.random.default_rng(5)
    views = []
    for k in range(3):
        img = rng.integers(0, 255, (16, 128), dtype=np.uint8)
        seg = rng.uniform(0, 40, (6, 2, 2))
        cloud = rng.normal(0, 10, (500, 3))
        views.append(
            ClosureView(img, img[::-1], 4, seg[:4], seg[4:], cloud + k, cloud, f"view {k}", ["a 1", "b 2"])
        )
    here = [(v, tmp_path / f"here_{i}.png") for i, v in enumerate(views)]
    there = [(v, tmp_path / f"there_{i}.png") for i, v in enumerate(views)]
    plot_closures(here, processes=1)
    plot_closures(there, processes=2)
    for (_, a), (_, b) in zip(here, there, strict=True):
        assert a.read_bytes() == b.read_bytes() and a.stat().st_size > 1000
