"""The `PlaceRecognizer` contract, checked on every registered pipeline with a few small simulated scans:
add, query with ``max_id``, queries leave the database alone, save / load into a fresh instance gives identical
answers, a wrong or truncated artifact is an `ArtifactError`, degenerate scans give no candidates or a
`ScanDataError`, and the loop-closure detector spends no id on a scan it refuses."""

from dataclasses import replace

import numpy as np
import pytest

from placerec.errors import ArtifactError, ScanDataError
from placerec.loop_closure import LoopClosureDetector
from placerec.recognizer import PIPELINES, Recognizer, make_pipeline
from placerec.sim import SimulatedSequence
from placerec.types import PlaceRecognizer, Scan

NAMES = sorted(PIPELINES)
#: Pipelines that use intensity: a scan whose valid points all have one intensity is a `ScanDataError` in them.
#: The geometry-only ones (scan-context, shot-votes, fpfh-votes, map-closures) ignore intensity and match such a
#: scan on its geometry, as any other.
USES_INTENSITY = {
    "orb-hbst",
    "brisk-hbst",
    "orb-dbow",
    "surf-dbow",
    "superpoint-dbow",
    "ishot-votes",
    "ishot-prob",
    "delight",
}


def _make(name):
    if name == "map-closures":
        pytest.importorskip("map_closures", reason="the optional peer 'map-closures' is not installed")
    return make_pipeline(name)


@pytest.fixture(scope="module")
def seq():
    return SimulatedSequence(world="town", sensor="vlp16", n_scans=4, seed=5, clutter=False)


@pytest.fixture(scope="module")
def scans(seq):
    return [seq[i] for i in range(len(seq))]


@pytest.fixture(scope="module", params=NAMES)
def built(request, seq, scans):
    """(name, recognizer with scans 0-2 added, descriptions of all scans)."""
    rec = _make(request.param)
    descriptions = [rec.describe(s) for s in scans]
    rec.add(0, scans[0], seq.poses[0])  # the scan-level API once
    for i in (1, 2):
        rec.add_description(i, descriptions[i], seq.poses[i])
    return request.param, rec, descriptions


def _answers(rec, descriptions, **kw):
    out = []
    for d in descriptions:
        cands = rec.query_description(d, k=3, query_id=7, **kw)
        out.append(
            [
                (
                    c.match_id,
                    round(c.score, 9),
                    None if c.relative_pose is None else c.relative_pose.round(6).tolist(),
                )
                for c in cands
            ]
        )
    return out


def test_every_pipeline_implements_the_one_protocol(built):
    name, rec, _ = built
    assert isinstance(rec, Recognizer) and isinstance(rec, PlaceRecognizer)
    assert isinstance(rec.frontend_key, str) and rec.frontend_key == _make(name).frontend_key


def test_query_finds_the_same_scan_and_respects_max_id(built, scans):
    name, rec, descriptions = built
    best = rec.query(scans[1], k=3, query_id=9)
    assert best and best[0].match_id == 1 and all(c.query_id == 9 for c in best)
    assert [c.score for c in best] == sorted((c.score for c in best), reverse=True)
    assert all(c.match_id <= 0 for c in rec.query_description(descriptions[1], k=3, max_id=0))
    assert rec.query_description(descriptions[1], k=3, max_id=-1) == []


def test_queries_leave_the_database_unchanged(built):
    name, rec, descriptions = built
    first = _answers(rec, descriptions)
    assert _answers(rec, descriptions) == first
    with pytest.raises(ScanDataError):  # id 2 is stored; a query must not have stored anything else either
        rec.add_description(2, descriptions[2])
    assert _answers(rec, descriptions) == first


def test_save_load_gives_identical_answers(built, tmp_path):
    name, rec, descriptions = built
    path = tmp_path / f"{name}.npz"
    rec.save(path)
    fresh = _make(name)
    fresh.load(path)
    assert _answers(fresh, descriptions) == _answers(rec, descriptions)
    assert _answers(fresh, descriptions, max_id=1) == _answers(rec, descriptions, max_id=1)


def test_wrong_or_truncated_artifacts_are_artifact_errors(built, tmp_path, scans):
    name, rec, _ = built
    other = make_pipeline("orb-hbst" if name == "scan-context" else "scan-context")
    other.add(0, scans[0])
    other.save(tmp_path / "other.npz")
    with pytest.raises(ArtifactError, match="other.npz"):
        _make(name).load(tmp_path / "other.npz")
    rec.save(tmp_path / "mine.npz")
    data = (tmp_path / "mine.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ArtifactError, match="cut.npz"):
        _make(name).load(tmp_path / "cut.npz")


def _degenerate(scan):
    n = len(scan)
    return {
        "blank organised": Scan(np.zeros((16 * 512, 3)), np.zeros(16 * 512), shape=(16, 512)),
        "at 1e30": Scan(np.full((n, 3), 1e30), scan.intensity),
        "10 points": scan.select(np.arange(10)),
        "empty": Scan(np.zeros((0, 3)), np.zeros(0)),
        "NaN": Scan(np.full((n, 3), np.nan), scan.intensity),
    }


def _no_candidates(rec, scan):
    try:
        return rec.query(scan, k=3) == []
    except ScanDataError:
        return True


def test_degenerate_scans_give_no_candidates(built, scans):
    name, rec, _ = built
    for what, bad in _degenerate(scans[0]).items():
        assert _no_candidates(rec, bad), f"{name}: a {what} scan matched"


def test_flat_intensity_is_refused_where_intensity_is_used_and_ignored_elsewhere(built, scans):
    name, rec, _ = built
    for value in (0.0, 0.5):
        flat = replace(scans[1], intensity=np.full(len(scans[1]), value, np.float32))
        if name in USES_INTENSITY:
            with pytest.raises(ScanDataError, match="intensity of the valid points is constant"):
                rec.query(flat, k=3)
        else:
            assert rec.query(flat, k=3)[0].match_id == 1, (
                f"{name}: flat intensity changed the geometry's match"
            )


@pytest.mark.parametrize("name", ["scan-context", "orb-hbst", "ishot-votes", "map-closures"])
def test_detector_spends_no_id_on_a_refused_scan(name, scans):
    det = LoopClosureDetector(_make(name), threshold=0.0, exclusion_frames=0)
    det.process(scans[0])
    with pytest.raises(ScanDataError):
        det.process(_degenerate(scans[0])["blank organised"])
    assert det.n_processed == 1
    det.process(scans[1])
    assert det.n_processed == 2 and det.last_max_id == 0
    assert det.skip() == 2 and det.n_processed == 3


def test_blank_scan_does_not_match_a_real_frame_in_scan_context(scans):
    rec = make_pipeline("scan-context")
    rec.add(0, scans[0])
    with pytest.raises(ScanDataError, match="valid points"):
        rec.query(Scan(np.zeros((64 * 1024, 3)), np.zeros(64 * 1024), shape=(64, 1024)))


def _rewritten(rec, src, dst, change):
    """A copy of the artifact ``src`` with ``change`` applied to its arrays (header kept)."""
    import sys

    from placerec.io.atomic import load_artifact, save_artifact

    module = sys.modules[type(rec).__module__]
    kind = getattr(module, "ARTIFACT_KIND", None) or module._KIND
    arrays, header = load_artifact(src, kind, tuple(range(1, 100)))  # whichever version it writes
    change(arrays)
    save_artifact(dst, kind, header["format_version"], arrays, header["meta"])
    return dst


def test_inconsistent_artifacts_are_artifact_errors(built, tmp_path):
    name, rec, _ = built
    rec.save(tmp_path / "db.npz")

    def duplicate_ids(a):
        a["ids"][1] = a["ids"][0]

    def inflated_counts(a):  # e.g. place 0 would claim every descriptor
        a["counts"][0] *= 1000

    changes = (duplicate_ids, inflated_counts) if name != "scan-context" else (duplicate_ids,)
    for change in changes:
        bad = _rewritten(rec, tmp_path / "db.npz", tmp_path / f"{change.__name__}.npz", change)
        with pytest.raises(ArtifactError, match=change.__name__):
            _make(name).load(bad)
