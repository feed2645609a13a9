"""Metrics (`placerec.eval`): fed NaN, empty and mismatched arrays, each function either refuses them with a
`ScanDataError` or returns the correct result (checked against a value computed by hand)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from fuzz.corpus import Case
from placerec.errors import ScanDataError


def _line(n: int, step: float = 1.0) -> np.ndarray:
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, 0, 3] = np.arange(n) * step
    return P


def _gt(n: int = 6) -> Any:
    from placerec.eval import loop_ground_truth
    from placerec.eval.exclusion import ExclusionWindow

    return loop_ground_truth(_line(n), gt_distance=2.0, exclusion=ExclusionWindow(frames=1))


def _loop(q: Any, m: Any, s: Any) -> Callable[[Any], Any]:
    from placerec.eval import loop_metrics

    return lambda args: loop_metrics(q, m, s, _gt())


def _is(value: Any) -> Callable[[Any, Any], None]:
    def check(args: Any, result: Any) -> None:
        if isinstance(value, float) and math.isnan(value):
            assert math.isnan(result), result
        else:
            np.testing.assert_allclose(result, value)

    return check


def _stats(expected: dict[str, float]) -> Callable[[Any, Any], None]:
    def check(args: Any, result: Any) -> None:
        assert set(expected) <= set(result), result
        for k, v in expected.items():
            if isinstance(v, float) and math.isnan(v):
                assert math.isnan(result[k]), (k, result[k])
            else:
                assert result[k] == v or np.isclose(result[k], v), (k, result[k], v)

    return check


def cases() -> list[Case]:
    from placerec.eval import (
        error_stats,
        localization_metrics,
        loop_ground_truth,
        pose_errors,
        positions_from_poses,
        timing_summary,
    )
    from placerec.eval.trajectory import ate, rpe, trajectory_errors

    out: list[Case] = []

    def case(name: str, run: Callable[[Any], Any], expect: str = "error", **kw: Any) -> None:
        out.append(Case("metrics", name, lambda t: None, run, expect, error=ScanDataError, **kw))

    nan = float("nan")
    # timing_summary
    case("timing/valid", lambda a: timing_summary([1.0, 2.0, 3.0]), "ok", check=_stats({"n": 3, "mean": 2.0, "max": 3.0}), fast=True)  # fmt: skip
    case("timing/empty", lambda a: timing_summary([]), "ok", check=_stats({"n": 0, "mean": nan}))
    case("timing/nan", lambda a: timing_summary([1.0, nan]))
    case("timing/inf", lambda a: timing_summary([1.0, float("inf")]))
    # error_stats: finite errors only (NaN rows are queries without an answer)
    case("error-stats/nan-rows", lambda a: error_stats(np.array([1.0, nan, 3.0])), "ok", check=_stats({"median": 2.0, "max": 3.0}))  # fmt: skip
    case("error-stats/empty", lambda a: error_stats(np.array([])), "ok", check=_stats({"median": nan}))
    # pose_errors
    case(
        "pose-errors/valid",
        lambda a: pose_errors(_line(3), _line(3, 2.0))[0],
        "ok",
        check=_is([0.0, 1.0, 2.0]),
    )
    case("pose-errors/mismatched", lambda a: pose_errors(_line(3), _line(4)))
    case("pose-errors/truth-nan", lambda a: pose_errors(_line(3), np.full((3, 4, 4), nan)))
    case("pose-errors/estimate-nan-row", lambda a: pose_errors(np.r_[_line(2), np.full((1, 4, 4), nan)], _line(3))[0], "ok", check=lambda a, r: np.isnan(r[2]) and r[0] == 0)  # fmt: skip
    case("pose-errors/not-4x4", lambda a: pose_errors(np.zeros((3, 3, 3)), np.zeros((3, 3, 3))))
    case("pose-errors/empty", lambda a: pose_errors(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))[0], "either", check=lambda a, r: r.shape == (0,))  # fmt: skip
    # trajectory errors
    case("ate/valid", lambda a: ate(_line(4), _line(4)), "ok", check=_is([0.0] * 4))
    case("ate/mismatched", lambda a: ate(_line(4), _line(5)))
    case("ate/nan", lambda a: ate(np.r_[_line(3), np.full((1, 4, 4), nan)], _line(4)))
    case("ate/empty", lambda a: ate(np.zeros((0, 4, 4)), np.zeros((0, 4, 4))))
    case("ate/one-pose", lambda a: ate(_line(1), _line(1)), "either", check=_is([0.0]))
    case("rpe/delta-0", lambda a: rpe(_line(4), _line(4), 0))
    case("rpe/delta-too-big", lambda a: rpe(_line(4), _line(4), 4))
    case("rpe/nan", lambda a: rpe(np.r_[_line(3), np.full((1, 4, 4), nan)], _line(4), 1))
    case("trajectory/one-pose", lambda a: trajectory_errors(_line(1), _line(1)))
    case("trajectory/valid", lambda a: trajectory_errors(_line(5), _line(5)).ate_rmse, "ok", check=_is(0.0))
    # ground truth and positions
    case("positions/nan", lambda a: positions_from_poses(np.full((2, 4, 4), nan)))
    case("positions/not-poses", lambda a: positions_from_poses(np.zeros((2, 3))), "either", check=lambda a, r: r.shape == (2, 3))  # fmt: skip
    case("ground-truth/nan-pose", lambda a: loop_ground_truth(np.r_[_line(3), np.full((1, 4, 4), nan)]))
    case("ground-truth/empty", lambda a: len(loop_ground_truth(np.zeros((0, 4, 4)))), "either", check=_is(0))
    case("ground-truth/distance-nan", lambda a: loop_ground_truth(_line(3), gt_distance=nan))
    case("ground-truth/distance-0", lambda a: loop_ground_truth(_line(3), gt_distance=0.0))
    case("ground-truth/yaw-nan", lambda a: loop_ground_truth(_line(3), gt_yaw_deg=nan))
    # loop metrics
    case("loop/valid", _loop([3, 4], [1, -1], [0.9, nan]), "ok", check=lambda a, r: r is not None)
    case("loop/empty", _loop([], [], []), "either", check=lambda a, r: r is not None)
    case("loop/mismatched", _loop([3, 4], [1], [0.9, 0.8]))
    case("loop/score-nan", _loop([3, 4], [1, 2], [0.9, nan]))
    case(
        "loop/score-inf",
        _loop([3, 4], [1, 2], [0.9, float("inf")]),
        "either",
        check=lambda a, r: r is not None,
    )
    case("loop/query-out-of-range", _loop([3, 60], [1, 2], [0.9, 0.8]))
    case("loop/query-negative", _loop([-3], [1], [0.9]))
    case("loop/query-repeated", _loop([3, 3], [1, 2], [0.9, 0.8]))
    case("loop/match-out-of-range", _loop([3], [99], [0.9]))
    case("loop/ids-float", _loop([3.5], [1], [0.9]))
    case("loop/ids-nan", _loop([nan], [1], [0.9]))
    # localisation metrics
    pos = np.array([[0.0, 0, 0], [10, 0, 0]])
    case("localization/valid", lambda a: localization_metrics(pos + [1, 0, 0], pos).success_rate, "ok", check=_is(1.0))  # fmt: skip
    case("localization/nan-answer", lambda a: localization_metrics(np.array([[nan] * 3, [10, 0, 0]]), pos).success_rate, "ok", check=_is(0.5))  # fmt: skip
    case("localization/mismatched", lambda a: localization_metrics(pos[:1], pos))
    case("localization/truth-nan", lambda a: localization_metrics(pos, np.array([[nan] * 3, [10, 0, 0]])))
    case("localization/empty", lambda a: localization_metrics(np.zeros((0, 3)), np.zeros((0, 3))).success_rate, "either", check=lambda a, r: r == 0 or math.isnan(r))  # fmt: skip
    case("localization/distance-nan", lambda a: localization_metrics(pos, pos, success_distance=nan))
    case("localization/distance-negative", lambda a: localization_metrics(pos, pos, success_distance=-1.0))
    case("localization/wrong-width", lambda a: localization_metrics(np.zeros((2, 5)), np.zeros((2, 5))))
    case("localization/basis-unknown", lambda a: localization_metrics(pos, pos, basis="magic"))
    return out
