import time

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.eval import (
    ExclusionWindow,
    evaluate_loop,
    localization_metrics,
    loop_ground_truth,
    loop_metrics,
    path_length,
    timing_summary,
)


def poses_from(xy, yaw_deg=None):
    """(N, 4, 4) poses at z = 0 from (N, 2) positions and optional headings."""
    xy = np.asarray(xy, dtype=np.float64)
    n = xy.shape[0]
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :2, 3] = xy
    if yaw_deg is not None:
        a = np.radians(np.asarray(yaw_deg, dtype=np.float64))
        P[:, 0, 0], P[:, 0, 1], P[:, 1, 0], P[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    return P


def square_lap():
    """A 40 m square, 1 m per frame, 160 frames: (0,0)->(40,0)->(40,40)->(0,40)->back towards (0,0)."""
    s = np.arange(160, dtype=np.float64)
    side, d = s // 40, s % 40
    x = np.select([side == 0, side == 1, side == 2, side == 3], [d, 40.0, 40.0 - d, 0.0])
    y = np.select([side == 0, side == 1, side == 2, side == 3], [0.0, d, 40.0, 40.0 - d])
    return np.stack([x, y], axis=1)


# ---------------------------------------------------------------- exclusion windows


def bounds(n, frames=None, seconds=None, metres=None, timestamps=None, positions=None):
    return ExclusionWindow(frames, seconds, metres).sequence_bounds(n, timestamps, positions)


def test_frame_window_edge_is_inclusive():
    b = bounds(300, frames=120)
    assert b[200] == 80  # exactly 120 frames older is eligible, 119 (index 81) is not
    assert b[119] == -1 and b[120] == 0
    assert np.all(b[:120] == -1)  # -1 is the one value for "nothing eligible"
    assert bounds(5, frames=0).tolist() == [-1, 0, 1, 2, 3]  # never the query itself
    assert bounds(5).tolist() == [-1, 0, 1, 2, 3]  # no limit at all: every older scan
    assert np.array_equal(ExclusionWindow().sequence_bounds(300), b)  # the default is 120 frames


def test_seconds_window_edge():
    t = np.arange(300) * 0.5  # 2 Hz: 60 s = 120 frames
    b = bounds(300, seconds=60.0, timestamps=t)
    assert b[200] == 80 and b[119] == -1 and b[120] == 0
    with pytest.raises(ScanDataError, match="seconds needs the timestamps"):
        bounds(300, seconds=60.0)
    with pytest.raises(ScanDataError, match="non-decreasing"):
        bounds(3, seconds=1.0, timestamps=[0.0, 2.0, 1.0])
    # equal timestamps with a zero window: still only older scans
    assert bounds(3, seconds=0.0, timestamps=[1.0, 1.0, 1.0]).tolist() == [-1, 0, 1]


def test_metres_window_edge_and_stops():
    xy = np.stack([np.arange(300.0), np.zeros(300)], axis=1)  # 1 m per frame
    b = bounds(300, metres=120.0, positions=np.c_[xy, np.zeros(300)])
    assert b[200] == 80 and b[119] == -1
    # standing still: no distance travelled, nothing becomes eligible during the stop
    xs = np.r_[np.arange(10.0), np.full(20, 9.0), 9.0 + np.arange(1.0, 11.0)]
    b = bounds(xs.size, metres=5.0, positions=np.c_[xs, np.zeros((xs.size, 2))])
    assert b[10] == 4 and b[29] == 4  # s = 9 during the stop: s_j <= 4 -> j <= 4
    assert b[30] == 5  # s = 10 -> s_j <= 5
    assert path_length(np.c_[xs, np.zeros((xs.size, 2))])[-1] == pytest.approx(19.0)
    with pytest.raises(ScanDataError, match="metres needs the positions"):
        bounds(300, metres=5.0)


def test_every_set_limit_applies():
    pos = np.c_[np.arange(10.0) * 2.0, np.zeros((10, 2))]  # 2 m and 1 s per frame
    t = np.arange(10.0)
    assert bounds(10, frames=1, seconds=0.0, metres=6.0, timestamps=t, positions=pos)[9] == 6  # metres bind
    assert bounds(10, frames=5, seconds=0.0, metres=6.0, timestamps=t, positions=pos)[9] == 4  # frames bind
    assert bounds(10, frames=1, seconds=4.0, metres=6.0, timestamps=t, positions=pos)[9] == 5  # seconds bind


@pytest.mark.parametrize(
    "bad", [{"frames": -1}, {"seconds": -0.5}, {"metres": float("nan")}, {"frames": 2.5}]
)
def test_invalid_window_is_a_config_error(bad):
    with pytest.raises(ConfigError, match=next(iter(bad))):
        ExclusionWindow(**{"frames": None, **bad})


# ---------------------------------------------------------------- ground truth


def test_ground_truth_square_driven_twice():
    lap = square_lap()
    gt = loop_ground_truth(poses_from(np.r_[lap, lap]), gt_distance=5.0)
    # lap 1, side 4 runs down x = 0 at (0, 160 - i); its nearest eligible scan (j <= i - 120) is scan 0 at (0, 0)
    assert gt.nearest_distance[150] == pytest.approx(10.0) and gt.nearest_index[150] == 0
    assert gt.nearest_distance[154] == pytest.approx(6.0) and not gt.is_revisit[154]
    assert gt.nearest_distance[155] == pytest.approx(5.0) and gt.is_revisit[155]
    expected = np.zeros(320, dtype=bool)
    expected[155:] = True  # 155..159 close the first lap, the whole second lap revisits
    assert np.array_equal(gt.is_revisit, expected)
    assert np.all(gt.nearest_distance[:120] == np.inf) and np.all(gt.nearest_index[:120] == -1)
    assert gt.n_revisits == 165
    # true matches of scan 300 (= scan 140's place): 139..141 ... within 5 m along side 4 of lap 1, all eligible
    assert gt.true_matches(300).tolist() == list(range(135, 146))
    assert gt.is_true_match(300, 140) and not gt.is_true_match(300, 100)
    assert gt.is_true_match([300, 300, 300], [140, -1, 299]).tolist() == [True, False, False]


def test_ground_truth_eligibility_edge_on_straight_line():
    xy = np.stack([np.arange(400) * 0.01, np.zeros(400)], axis=1)  # everything within 4 m
    gt = loop_ground_truth(poses_from(xy), exclusion=ExclusionWindow(frames=120))
    assert gt.is_true_match(200, 80) and not gt.is_true_match(200, 81)
    assert gt.is_revisit[120] and not gt.is_revisit[119]
    assert gt.true_matches(200).tolist() == list(range(81))


def test_ground_truth_yaw_limit():
    lap = square_lap()
    yaw = np.r_[np.zeros(160), np.full(160, 180.0)]  # second lap driven with the opposite heading
    poses = poses_from(np.r_[lap, lap], yaw)
    gt = loop_ground_truth(poses, gt_distance=5.0, gt_yaw_deg=30.0)
    expected = np.zeros(320, dtype=bool)
    expected[155:160] = True  # lap 1 closing on lap 1 (same heading)
    expected[315:320] = True  # lap 2 closing on its own start (scans 160..164, same heading)
    assert np.array_equal(gt.is_revisit, expected)
    assert not gt.is_true_match(300, 140) and gt.is_true_match(317, 160)
    assert loop_ground_truth(poses).is_true_match(300, 140)  # no yaw limit
    # the heading difference wraps: 179 deg vs -179 deg differ by 2 deg
    wrap = loop_ground_truth(
        poses_from([[0, 0], [1, 0]], [179.0, -179.0]), gt_yaw_deg=5.0, exclusion=ExclusionWindow(frames=1)
    )
    assert wrap.is_revisit.tolist() == [False, True]


def test_ground_truth_planar_vs_3d():
    P = poses_from([[0, 0], [0, 0]])
    P[1, 2, 3] = 4.0  # 4 m above
    one = ExclusionWindow(frames=1)
    assert loop_ground_truth(P, gt_distance=3.0, exclusion=one).is_revisit[1] == False  # noqa: E712
    assert loop_ground_truth(P, gt_distance=3.0, exclusion=one, planar=True).is_revisit[1]


def test_ground_truth_matches_brute_force_on_random_walk():
    rng = np.random.default_rng(3)
    n = 5000
    xy = np.cumsum(rng.normal(size=(n, 2)), axis=0) * 0.8
    t0 = time.perf_counter()
    gt = loop_ground_truth(poses_from(xy), gt_distance=5.0, exclusion=ExclusionWindow(frames=120))
    elapsed = time.perf_counter() - t0
    idx = np.arange(n)
    for i in rng.choice(np.arange(120, n), 40, replace=False):
        d = np.linalg.norm(xy[: i - 119] - xy[i], axis=1)
        assert gt.nearest_distance[i] == pytest.approx(d.min())
        assert gt.is_revisit[i] == (d.min() <= 5.0)
        assert gt.true_matches(i).tolist() == idx[: i - 119][d <= 5.0].tolist()
    assert elapsed < 2.0


# ---------------------------------------------------------------- loop metrics


def hand_gt():
    """Scans 0..4 far apart (100 m), scans 5..9 revisit scan i-5 at 1 m, scans 10, 11 far from everything.
    Window 5 frames: scans 5..9 are revisits whose only true match is i - 5; 0..4, 10, 11 are not revisits."""
    x = np.r_[np.arange(5) * 100.0, np.arange(5) * 100.0 + 1.0, 1000.0, 2000.0]
    return loop_ground_truth(
        poses_from(np.c_[x, np.zeros(12)]), gt_distance=5.0, exclusion=ExclusionWindow(frames=5)
    )


Q = [5, 6, 7, 8, 9, 10, 11]
M = [0, 0, 2, -1, 4, 1, 3]  # correct, wrong (revisit), correct, none, correct, wrong, wrong
S = [0.9, 0.8, 0.7, np.nan, 0.3, 0.6, 0.7]


def test_pr_curve_hand_computed():
    gt = hand_gt()
    assert gt.is_revisit.tolist() == [False] * 5 + [True] * 5 + [False] * 2
    m = loop_metrics(Q, M, S, gt)
    # sorted: 0.9 c | 0.8 w | 0.7 c, 0.7 w | 0.6 w | 0.3 c ; 5 revisits
    # t=0.9: TP1 FP0 FN4 | t=0.8: TP1 FP1 FN4 (q6 is FP and FN) | t=0.7: TP2 FP2 FN3 | t=0.6: TP2 FP3 FN3
    # t=0.3: TP3 FP3 FN2
    assert m.thresholds.tolist() == [0.9, 0.8, 0.7, 0.6, 0.3]
    assert m.tp.tolist() == [1, 1, 2, 2, 3]
    assert m.fp.tolist() == [0, 1, 2, 3, 3]
    assert m.fn.tolist() == [4, 4, 3, 3, 2]
    np.testing.assert_allclose(m.precision, [1.0, 0.5, 0.5, 0.4, 0.5])
    np.testing.assert_allclose(m.recall, [0.2, 0.2, 0.4, 0.4, 0.6])
    np.testing.assert_allclose(m.f1, [1 / 3, 2 / 7, 4 / 9, 0.4, 6 / 11])
    assert m.max_f1 == pytest.approx(6 / 11)
    assert (m.precision_at_max_f1, m.recall_at_max_f1, m.threshold_at_max_f1) == pytest.approx(
        (0.5, 0.6, 0.3)
    )
    # AP = 0.2 * 1.0 + 0 * 0.5 + 0.2 * 0.5 + 0 * 0.4 + 0.2 * 0.5
    assert m.average_precision == pytest.approx(0.4)
    assert m.recall_at_1 == pytest.approx(0.6)
    assert (m.n_queries, m.n_revisits, m.n_candidates, m.no_revisits) == (7, 5, 6, False)
    assert m.correct.tolist() == [True, False, True, False, True, False, False]


def test_confusion_at_threshold():
    m = loop_metrics(Q, M, S, hand_gt())
    # at 0.7: accepted q5 (c), q6 (w), q7 (c), q11 (w); revisits q6, q8, q9 missed; q10 rejected and no revisit
    assert m.confusion_at(0.7) == {"tp": 2, "fp": 2, "fn": 3, "tn": 1}
    out = m.outcomes_at(0.7)
    assert out["fp"].tolist() == [False, True, False, False, False, False, True]
    assert (out["fp"] & out["fn"]).tolist() == [False, True, False, False, False, False, False]
    assert m.confusion_at(np.inf) == {"tp": 0, "fp": 0, "fn": 5, "tn": 2}


def test_recall_at_n():
    top = np.array(
        [
            [0, -1, -1],  # q5: hit at 1
            [0, 2, 1],  # q6: true match 1 at rank 3
            [2, 0, -1],  # q7: hit at 1
            [-1, -1, -1],  # q8: nothing
            [4, 3, 2],  # q9: hit at 1
            [1, 0, 2],  # q10: not a revisit
            [3, 2, 1],  # q11: not a revisit
        ]
    )
    m = loop_metrics(Q, M, S, hand_gt(), topn_match_ids=top)
    np.testing.assert_allclose(m.recall_at_n, [0.6, 0.6, 0.8])
    assert m.summary()["recall_at_n"] == pytest.approx([0.6, 0.6, 0.8])
    with pytest.raises(ScanDataError):
        loop_metrics(Q, M, S, hand_gt(), topn_match_ids=top[:3])


def test_perfect_ranking_has_unit_ap():
    gt = hand_gt()
    m = loop_metrics([5, 6, 7, 8, 9, 10], [0, 1, 2, 3, 4, 0], [0.9, 0.8, 0.7, 0.6, 0.5, 0.1], gt)
    assert m.average_precision == pytest.approx(1.0)
    assert m.max_f1 == pytest.approx(1.0) and m.threshold_at_max_f1 == pytest.approx(0.5)


def test_all_scores_equal_give_one_point():
    m = loop_metrics(Q, [0, 1, 2, 3, 0, 1, 3], np.full(7, 0.5), hand_gt())
    # q5..q8 point at their true matches; q9, q10, q11 are wrong
    assert m.thresholds.tolist() == [0.5]
    assert (m.tp.tolist(), m.fp.tolist(), m.fn.tolist()) == ([4], [3], [1])
    assert m.max_f1 == pytest.approx(2 * (4 / 7) * 0.8 / (4 / 7 + 0.8))


def test_no_candidates():
    m = loop_metrics(Q, [-1] * 7, [np.nan] * 7, hand_gt())
    assert m.thresholds.size == 0 and m.max_f1 == 0.0 and m.average_precision == 0.0
    assert m.recall_at_1 == 0.0 and np.isnan(m.threshold_at_max_f1)
    assert m.confusion_at(0.0)["fn"] == 5


def test_no_revisits_flagged():
    m = loop_metrics([10, 11], [1, 2], [0.5, 0.4], hand_gt())
    assert m.no_revisits and m.n_revisits == 0
    assert m.recall.tolist() == [0.0, 0.0] and m.precision.tolist() == [0.0, 0.0]
    assert m.max_f1 == 0.0 and m.recall_at_1 == 0.0


def test_recall_at_100_precision_and_extended_precision_hand_computed():
    gt = hand_gt()
    # the PR example: precision 1 only at the first point (R 0.2), then a false positive
    m = loop_metrics(Q, M, S, gt)
    assert (m.recall_at_100_precision, m.precision_at_min_recall) == pytest.approx((0.2, 1.0))
    assert m.extended_precision == pytest.approx(0.6)
    # 4 revisits (q5, q6, q7, q9), three true closures before the first false one: R_P100 = 3/4, EP = 0.875
    m = loop_metrics([5, 6, 7, 9, 10], [0, 1, 2, 0, 1], [0.9, 0.85, 0.8, 0.7, 0.75], gt)
    assert m.precision.tolist() == pytest.approx([1.0, 1.0, 1.0, 0.75, 0.6])
    assert m.recall.tolist() == pytest.approx([0.25, 0.5, 0.75, 0.75, 0.75])
    assert (m.recall_at_100_precision, m.precision_at_min_recall) == pytest.approx((0.75, 1.0))
    assert m.extended_precision == pytest.approx(0.875)
    # the best-scored candidate is wrong: no point at precision 1, P_R0 = 0
    m = loop_metrics([5, 10], [0, 1], [0.5, 0.9], gt)
    assert (m.recall_at_100_precision, m.precision_at_min_recall, m.extended_precision) == (0.0, 0.0, 0.0)
    # a tie at the top score between a true and a false closure: P_R0 = 1/2, R_P100 = 0
    m = loop_metrics([5, 10], [0, 1], [0.9, 0.9], gt)
    assert (m.recall_at_100_precision, m.precision_at_min_recall, m.extended_precision) == (0.0, 0.5, 0.25)
    summary = m.summary()
    assert (summary["recall_at_100_precision"], summary["extended_precision"]) == (0.0, 0.25)
    none = loop_metrics(Q, [-1] * 7, [np.nan] * 7, gt)
    assert (none.recall_at_100_precision, none.precision_at_min_recall, none.extended_precision) == (0, 0, 0)


def test_bad_inputs_raise_placerec_errors():
    gt = hand_gt()
    with pytest.raises(ScanDataError, match="NaN"):
        loop_metrics([5, 6], [0, 1], [0.5, np.nan], gt)
    with pytest.raises(ScanDataError, match="once"):
        loop_metrics([5, 5], [0, 0], [0.5, 0.5], gt)
    with pytest.raises(ScanDataError):
        loop_metrics([5, 6], [0], [0.5], gt)
    with pytest.raises(ScanDataError):
        loop_metrics([50], [0], [0.5], gt)
    with pytest.raises(ValueError):  # ScanDataError is a ValueError
        loop_metrics([5], [0.5], [0.5], gt)


def test_candidate_inside_exclusion_window_is_a_false_positive():
    gt = hand_gt()
    m = loop_metrics([6], [5], [0.9], gt)  # scan 5 is 99 m away anyway but also too recent
    assert m.fp.tolist() == [1] and m.tp.tolist() == [0]
    near = loop_ground_truth(poses_from(np.zeros((10, 2))), exclusion=ExclusionWindow(frames=5))
    assert loop_metrics([9], [8], [1.0], near).fp.tolist() == [1]  # same place, but too recent
    assert loop_metrics([9], [4], [1.0], near).tp.tolist() == [1]


def test_evaluate_loop_from_csv_like_arrays(tmp_path):
    csv = tmp_path / "c.csv"
    rows = "\n".join(f"{q},{m},{s}" for q, m, s in zip(Q, M, S, strict=True))
    csv.write_text("query_id,match_id,score\n" + rows + "\n")
    data = np.genfromtxt(csv, delimiter=",", names=True)
    x = np.r_[np.arange(5) * 100.0, np.arange(5) * 100.0 + 1.0, 1000.0, 2000.0]
    m, gt = evaluate_loop(
        data["query_id"],
        data["match_id"],
        data["score"],
        poses_from(np.c_[x, np.zeros(12)]),
        exclusion=ExclusionWindow(frames=5),
    )
    assert m.max_f1 == pytest.approx(6 / 11) and gt.n_revisits == 5


# ---------------------------------------------------------------- localisation and timing


def test_localization_metrics():
    truth = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0]], dtype=float)
    est = np.array([[1, 2, 2], [10, 3.5, 0], [np.nan] * 3, [30, 0, 10]], dtype=float)
    m = localization_metrics(est, truth, success_distance=3.0)
    np.testing.assert_allclose(m.errors, [3.0, 3.5, np.inf, 10.0])
    assert m.success.tolist() == [True, False, False, False]  # exactly 3 m succeeds
    assert m.success_rate == 0.25 and m.n_no_estimate == 1
    # each query is one of localised / no answer / answered wrongly: 1 + 1 + 2 (3.5 m and 10 m off)
    assert (m.n_success, m.n_no_estimate, m.n_wrong) == (1, 1, 2)
    assert m.answered.tolist() == [True, True, False, True]
    assert (m.no_answer_rate, m.wrong_rate) == (0.25, 0.5)
    s = m.summary()
    assert (s["n_wrong"], s["no_answer_rate"], s["wrong_rate"]) == (2, 0.25, 0.5)
    assert s["answer_rule"] == "accepted"
    planar = localization_metrics(est, truth, planar=True, answer_rule="top")
    assert (planar.n_success, planar.n_no_estimate, planar.n_wrong, planar.answer_rule) == (2, 1, 1, "top")
    assert m.mean_error == pytest.approx((3 + 3.5 + 10) / 3) and m.median_error == pytest.approx(3.5)
    assert localization_metrics(est, truth, planar=True).success.tolist() == [True, False, False, True]
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, 3] = truth
    assert localization_metrics(poses, truth).success.all()
    with pytest.raises(ScanDataError):
        localization_metrics(est[:2], truth)
    with pytest.raises(ScanDataError, match="answer_rule"):
        localization_metrics(est, truth, answer_rule="rejected")


def test_localization_metrics_without_queries_or_answers():
    empty = localization_metrics(np.zeros((0, 3)), np.zeros((0, 3)))
    assert (empty.n_wrong, empty.no_answer_rate, empty.wrong_rate, empty.success_rate) == (0, 0.0, 0.0, 0.0)
    none = localization_metrics(np.full((3, 3), np.nan), np.zeros((3, 3)))
    assert (none.n_success, none.n_no_estimate, none.n_wrong, none.no_answer_rate) == (0, 3, 0, 1.0)


def test_timing_summary():
    t = timing_summary(np.arange(1, 101, dtype=float))
    assert t["n"] == 100 and t["mean"] == pytest.approx(50.5) and t["median"] == pytest.approx(50.5)
    assert t["p95"] == pytest.approx(95.05) and t["max"] == 100.0
    assert timing_summary([])["n"] == 0 and np.isnan(timing_summary([])["mean"])
    with pytest.raises(ScanDataError):
        timing_summary([1.0, np.nan])
