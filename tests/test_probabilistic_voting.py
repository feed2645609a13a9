"""The ISHOT paper's probabilistic voting (Sec. IV-C to IV-F): vote model fit (eq. 7), posterior (eq. 6), the
early-stopping query, and the fit-votes / build-places commands."""

import math

import numpy as np
import pytest
from synthetic_places import add_synthetic_places
from typer.testing import CliRunner

from placerec.cli import app
from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.params import deep_merge
from placerec.pipelines.probabilistic_voting import ProbabilisticVoting
from placerec.three_d.places import PlacesDatabase
from placerec.three_d.posterior import Posterior, PosteriorTable, density_weights
from placerec.three_d.vote_model import (
    VoteModel,
    VoteModelParams,
    fit_vote_model,
    mixture_cdf,
    mixture_pdf,
)


def _mixture_sample(rng, n, sigma, lam, d_max):
    near = np.abs(rng.normal(0.0, sigma, n))
    far = rng.uniform(0.0, d_max, n)
    return np.where(rng.random(n) < lam, np.minimum(near, d_max), far)


def test_fit_recovers_known_sigma_and_lambda_per_tau_range():
    rng = np.random.default_rng(3)
    truth = {0: (3.0, 0.7), 1: (6.0, 0.35), 2: (10.0, 0.1)}
    d_max = 400.0
    d, tau = [], []
    for r, (sigma, lam) in truth.items():
        d.append(_mixture_sample(rng, 6000, sigma, lam, d_max))
        tau.append(rng.uniform([0.0, 0.8, 0.9][r], [0.8, 0.9, 1.0][r], 6000))
    model = fit_vote_model(
        np.concatenate(d), np.concatenate(tau), d_max, VoteModelParams(tau_edges=[0, 0.8, 0.9, 1])
    )
    for r, (sigma, lam) in truth.items():
        assert model.sigma[r] == pytest.approx(sigma, rel=0.08), r
        assert model.lam[r] == pytest.approx(lam, abs=0.03), r
    assert model.n_votes.tolist() == [6000, 6000, 6000]


def test_a_range_with_too_few_votes_carries_no_information():
    rng = np.random.default_rng(0)
    d = _mixture_sample(rng, 500, 3.0, 0.6, 200.0)
    tau = np.full(500, 0.5)
    tau[:5] = 0.95
    model = fit_vote_model(d, tau, 200.0, VoteModelParams(tau_edges=[0, 0.9, 1], min_votes=30))
    assert model.lam[1] == 0.0 and model.lam[0] > 0.4


def test_mixture_cdf_is_the_integral_of_the_pdf():
    d_max, sigma, lam = 150.0, 4.0, 0.6
    x = np.linspace(0, d_max, 200001)
    pdf = mixture_pdf(x, sigma, lam, d_max)
    integral = np.concatenate([[0], np.cumsum((pdf[1:] + pdf[:-1]) / 2 * np.diff(x))])
    assert np.allclose(integral, mixture_cdf(x, sigma, lam, d_max), atol=1e-6)
    assert mixture_cdf(np.array([d_max]), sigma, lam, d_max)[0] == pytest.approx(1.0, abs=1e-9)
    # the half-normal at 0: sqrt(2) / (sigma sqrt(pi))
    assert mixture_pdf(np.array([0.0]), sigma, 1.0, d_max)[0] == pytest.approx(math.sqrt(2 / math.pi) / sigma)


def _model():
    return VoteModel([0.0, 0.8, 1.0], [3.0, 8.0], [0.7, 0.2], 300.0)


def test_posterior_vector_is_eq7_normalised_over_places_and_sparse_matches_full():
    model = _model()
    xyz = np.c_[np.arange(200) * 5.0, np.zeros(200), np.zeros(200)]
    full, sparse = PosteriorTable(model, xyz, "full"), PosteriorTable(model, xyz, "sparse")
    for v, r in ((0, 0), (30, 1), (199, 0)):
        d = np.abs(xyz[:, 0] - xyz[v, 0])
        expect = model.pdf(d, r) / model.pdf(d, r).sum()
        assert np.allclose(full.vector(v, r), expect, rtol=1e-5)
        assert np.allclose(sparse.vector(v, r), expect, rtol=2e-3)
    assert sparse.nbytes < full.nbytes / 10


def test_eq6_is_the_normalised_product_of_the_vote_vectors():
    model = _model()
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 100, (25, 3))
    table = PosteriorTable(model, xyz, "full")
    voted, ranges = rng.integers(0, 25, 12), rng.integers(0, 2, 12)
    post = Posterior(table)
    post.update(voted[:5], ranges[:5])
    post.update(voted[5:], ranges[5:])
    prod = np.prod([table.vector(v, r) for v, r in zip(voted, ranges, strict=True)], axis=0)
    assert np.allclose(post.probabilities, prod / prod.sum(), rtol=1e-5)
    assert post.n_votes == 12
    sparse = Posterior(PosteriorTable(model, xyz, "sparse"))
    sparse.update(voted, ranges)
    assert np.allclose(sparse.probabilities, post.probabilities, rtol=1e-2, atol=1e-6)


def test_keypoint_density_correction_weights_dense_places_down():
    w = density_weights(np.array([100, 200, 50, 0]))
    assert w.tolist() == pytest.approx([350 / 3 / 100, 350 / 3 / 200, 350 / 3 / 50, 0.0])
    model = _model()
    xyz = np.c_[np.arange(3) * 100.0, np.zeros(3), np.zeros(3)]
    post = Posterior(PosteriorTable(model, xyz, "full"), weights=np.array([0.5, 1.0, 1.0]))
    post.update([0, 0, 1], [0, 0, 0])  # two half-weight votes for place 0 equal one vote for place 1
    p = post.probabilities
    assert p[0] == pytest.approx(p[1], rel=1e-5) and p[2] < p[0]


def test_scale_is_evidence_against_the_masked_places():
    model = _model()
    xyz = np.c_[np.arange(4) * 100.0, np.zeros(4), np.zeros(4)]
    post = Posterior(PosteriorTable(model, xyz, "full"))
    post.update([0, 0, 1], [0, 0, 0])
    before = post.probabilities
    post.scale(np.array([True, False, False, False]), 0.1)
    expect = before * np.array([0.1, 1, 1, 1])
    assert np.allclose(post.probabilities, expect / expect.sum(), rtol=1e-9)
    with pytest.raises(ScanDataError):
        post.scale(np.ones(4, bool), 0.0)


def test_vote_model_round_trip_and_corrupt_file(tmp_path):
    rng = np.random.default_rng(2)
    model = fit_vote_model(_mixture_sample(rng, 400, 3.0, 0.6, 100.0), rng.uniform(0, 1, 400), 100.0,
                           VoteModelParams(tau_edges=[0, 0.5, 1]), {"what": "test"})  # fmt: skip
    model.save(tmp_path / "m.npz")
    back = VoteModel.load(tmp_path / "m.npz")
    assert np.array_equal(back.sigma, model.sigma) and np.array_equal(back.lam, model.lam)
    assert back.d_max == 100.0 and back.provenance["what"] == "test" and "created" in back.provenance
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ArtifactError):
        VoteModel.load(tmp_path / "bad.npz")
    with pytest.raises(ConfigError):
        VoteModel([0, 1], [1.0], [1.0], 10.0)  # lambda must stay below 1


def _synthetic_db(rec, rng):
    return add_synthetic_places(rec, rng, n_places=20, per_place=40, dim=1344)


def test_early_stop_consumes_one_batch_and_exhaustive_consumes_all():
    rng = np.random.default_rng(4)
    common = {"verify": {"enabled": False}, "model": {"tau_edges": [0, 0.8, 1], "sigma": [4, 8],
              "lam": [0.8, 0.1], "d_max": 100}}  # fmt: skip
    early = ProbabilisticVoting(common)
    descs = _synthetic_db(early, rng)
    query = descs[7][:32] + 0.02 * rng.normal(size=(32, 1344)).astype(np.float32)
    desc = {"keypoints": np.zeros((32, 3)), "descriptors": query}
    top = early.query_description(desc, k=3)[0]
    assert top.match_id == 7 and top.extra["early_stop"] and top.extra["keypoints_consumed"] == 16
    assert top.extra["posterior"] > 0.15
    exhaustive = ProbabilisticVoting(common, early_stop=False)
    _synthetic_db(exhaustive, np.random.default_rng(4))
    top = exhaustive.query_description(desc, k=3)[0]
    assert top.match_id == 7 and not top.extra["early_stop"] and top.extra["keypoints_consumed"] == 32
    # max_id: place 7 and later are out of reach; the posterior goes to an eligible place
    assert all(c.match_id <= 5 for c in early.query_description(desc, k=3, max_id=5))


def test_verify_separation_spreads_the_verified_places():
    rng = np.random.default_rng(4)
    common = {"verify": {"enabled": False, "top_k": 3}, "model": {"tau_edges": [0, 0.8, 1], "sigma": [12, 20],
              "lam": [0.8, 0.5], "d_max": 100}}  # fmt: skip
    descs = _synthetic_db(ProbabilisticVoting(common), rng)
    query = descs[7][:16] + 0.02 * rng.normal(size=(16, 1344)).astype(np.float32)
    desc = {"keypoints": np.zeros((16, 3)), "descriptors": query}
    xs = {}
    for sep in (0.0, 12.0):
        rec = ProbabilisticVoting(common, verify={"separation_m": sep})
        _synthetic_db(rec, np.random.default_rng(4))
        xs[sep] = [5.0 * c.match_id for c in rec.query_description(desc, k=3)]
    assert xs[0.0][0] == xs[12.0][0] == 35.0  # place 7 first either way
    assert min(abs(a - b) for a in xs[0.0] for b in xs[0.0] if a != b) == 5.0  # its neighbours next
    assert all(abs(a - b) >= 12.0 for a in xs[12.0] for b in xs[12.0] if a != b) and len(xs[12.0]) == 3


def test_stop_radius_tests_the_posterior_of_each_region():
    common = {"verify": {"enabled": False}}
    rec = ProbabilisticVoting(common, stop_radius_m=5.0)
    _synthetic_db(rec, np.random.default_rng(4))  # places 5 m apart on a line
    prob = np.random.default_rng(0).dirichlet(np.ones(20))
    padded = np.r_[0.0, prob, 0.0]
    assert np.allclose(
        rec.stop_mass(prob), padded[:-2] + padded[1:-1] + padded[2:]
    )  # each place and its neighbours
    rec0 = ProbabilisticVoting(common)
    _synthetic_db(rec0, np.random.default_rng(4))
    assert rec0.stop_mass(prob) is prob  # the paper's test: each place alone


def test_a_rejection_sends_the_stop_to_the_next_place_without_more_keypoints():
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=5, seed=5, clutter=False, spacing=2.0)
    # every candidate is rejected (eps_ICP ~ 0) and every batch passes the stop test (xi_v ~ 0)
    strict = {"xi_v": 1e-9, "verify": {"top_k": 1, "score": {"eps_icp": 1e-12}}}
    descs = None
    consumed = {}
    for weight in (1.0, 1e-6):
        rec = ProbabilisticVoting(strict, reject_weight=weight)
        descs = descs or {i: rec.describe(seq[i]) for i in range(5)}
        for i in (0, 2, 3, 4):
            rec.add_description(i, descs[i], seq.poses[i])
        cands = rec.query_description(descs[1], k=10, query_id=1)
        assert len(cands) == 4 and not any(c.accepted for c in cands)
        assert cands[0].extra["n_verified"] == 4
        consumed[weight] = cands[0].extra["keypoints_consumed"]
    n = cands[0].extra["n_keypoints"]
    assert n > 80
    # the paper's query verifies one place per batch, then one more batch finds nothing left to verify
    assert consumed[1.0] == 80
    # a rejection is evidence against its place: the next one passes the test on the first batch's votes
    assert consumed[1e-6] == 16


def test_localises_a_simulated_scan_with_a_6dof_pose():
    from placerec.sim import SimulatedSequence
    from placerec.types import relative_pose

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=5, seed=5, clutter=False, spacing=2.0)
    rec = ProbabilisticVoting()
    for i in (0, 2, 4):
        rec.add(i, seq[i], seq.poses[i])
    cands = rec.query(seq[1], k=1, query_id=1)
    assert cands and cands[0].accepted
    c = cands[0]
    gt = relative_pose(seq.poses[c.match_id], seq.poses[1])
    assert np.linalg.norm(c.relative_pose[:3, 3] - gt[:3, 3]) < 0.3
    assert np.linalg.norm(c.T_world_query[:3, 3] - seq.poses[1][:3, 3]) < 0.3
    assert 0 < c.extra["keypoints_consumed"] <= c.extra["n_keypoints"]


def test_fallback_verifies_fallback_top_k_places():
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=5, seed=5, clutter=False, spacing=2.0)
    # nothing can be accepted (eps_ICP ~ 0) and nothing stops early: the fallback verifies the only candidates
    strict = {"early_stop": False, "verify": {"top_k": 1, "score": {"eps_icp": 1e-12}}}
    descs = None
    for fallback, expected in ((None, 1), (3, 3)):
        rec = ProbabilisticVoting(deep_merge(strict, {"verify": {"fallback_top_k": fallback}}))
        descs = descs or {i: rec.describe(seq[i]) for i in range(5)}
        for i in (0, 2, 3, 4):
            rec.add_description(i, descs[i], seq.poses[i])
        cands = rec.query_description(descs[1], k=10, query_id=1)
        assert len(cands) == expected and not any(c.accepted for c in cands)
        assert all(c.verification.correspondences > 0 for c in cands)  # each went through verification


def test_build_places_and_fit_votes_commands(tmp_path):
    runner = CliRunner()
    places, model, fig = tmp_path / "places.npz", tmp_path / "votes.npz", tmp_path / "votes.png"
    res = runner.invoke(app, ["build-places", "--sim-world", "town", "--sim-scans", "12", "--set", "window_m=0",
                              "--out", str(places)])  # fmt: skip
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["fit-votes", "--places", str(places), "--sim-world", "town", "--sim-scans", "12",
                              "--n-training", "1", "--set", "min_votes=5", "--set", "tau_edges=[0, 0.9, 1]",
                              "--out", str(model), "--figure", str(fig)])  # fmt: skip
    assert res.exit_code == 0, res.output
    m = VoteModel.load(model)
    assert m.n_ranges == 2 and m.provenance["places_file"] == str(places) and fig.stat().st_size > 0
    assert m.provenance["n_training_scans"] == 3
    rec = ProbabilisticVoting(vote_model=str(model), places={"database": str(places)})
    assert rec.vote_model.n_ranges == 2 and len(rec) == len(PlacesDatabase.load(places))
    # a map other than the one the places were built from is refused
    res = runner.invoke(app, ["fit-votes", "--places", str(places), "--sim-world", "town", "--sim-scans", "20",
                              "--out", str(model)])  # fmt: skip
    assert res.exit_code == 2 and "another map" in res.output


def test_training_draw_gives_other_query_spots_in_the_same_map():
    from placerec.sim import make_localization_split

    a = make_localization_split("town", "vlp16", 0, n_queries=3, n_map=20, conditions=("gator",))
    b = make_localization_split("town", "vlp16", 0, n_queries=3, n_map=20, conditions=("gator",), draw=1)
    assert np.array_equal(a.map.poses, b.map.poses)
    assert not np.allclose(a.queries["gator"].poses, b.queries["gator"].poses)
    assert b.queries["gator"].name.endswith("-draw1")


def test_ivf_and_pca_indices_find_the_neighbours_and_the_pipeline_agrees():
    from placerec.pipelines.keypoint_voting import IvfIndex, knn2

    rng = np.random.default_rng(6)
    x = rng.normal(size=(3000, 64)).astype(np.float32)
    q = x[:50] + 0.01 * rng.normal(size=(50, 64)).astype(np.float32)
    d, i = IvfIndex(x, nlist=20, nprobe=4).knn2(q)
    d0, i0 = knn2(q, x)
    assert np.array_equal(i[:, 0], i0[:, 0]) and np.allclose(d[:, 0], d0[:, 0], atol=1e-4)
    common = {"verify": {"enabled": False}, "model": {"tau_edges": [0, 0.8, 1], "sigma": [4, 8],
              "lam": [0.8, 0.1], "d_max": 100}}  # fmt: skip
    flat, ivf, pca = (
        ProbabilisticVoting(common),
        ProbabilisticVoting(common, search={"index": "ivf", "ivf_nlist": 8}),
        ProbabilisticVoting(common, search={"index": "pca", "pca_dims": 64}),
    )
    descs = _synthetic_db(flat, np.random.default_rng(4))
    _synthetic_db(ivf, np.random.default_rng(4))
    _synthetic_db(pca, np.random.default_rng(4))
    query = descs[3][:32] + 0.02 * rng.normal(size=(32, 1344)).astype(np.float32)
    desc = {"keypoints": np.zeros((32, 3)), "descriptors": query}
    assert flat.query_description(desc)[0].match_id == ivf.query_description(desc)[0].match_id == 3
    a, b = flat.query_description(desc, k=3), pca.query_description(desc, k=3)  # exact: the same posterior
    assert [c.match_id for c in a] == [c.match_id for c in b]
    assert np.allclose([c.extra["posterior"] for c in a], [c.extra["posterior"] for c in b], rtol=1e-5)


def test_verifying_one_at_a_time_stops_at_the_first_accepted_place():
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=7, seed=5, clutter=False, spacing=2.0)
    descs = None
    verified = {}
    for at_once in (None, 1):
        rec = ProbabilisticVoting(verify={"top_k": 3, "at_once": at_once})
        descs = descs or {i: rec.describe(seq[i]) for i in range(7)}
        for i in (0, 2, 4, 6):
            rec.add_description(i, descs[i], seq.poses[i])
        cands = rec.query_description(descs[1], k=5, query_id=1)
        assert cands[0].accepted and cands[0].match_id in (0, 2)
        verified[at_once] = cands[0].extra["n_verified"]
    assert verified[None] == 3 and verified[1] == 1
