"""Compact descriptor and cloud storage: the quantisers' error bounds, search on the compressed store against float32,
save/load of places databases and keypoint-voting databases in each store, and corrupt quantisers in saved files."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_places import add_synthetic_places

from placerec.errors import ArtifactError, ConfigError
from placerec.io.atomic import load_artifact, save_artifact
from placerec.pipelines.keypoint_voting import KeypointVoting
from placerec.quantise import FixedPointCloud, ScalarQuantiser, decode_unit, encode_unit
from placerec.retrieval.descriptor_store import BLAS_BATCH, DescriptorStore, knn2, sq_norms
from placerec.three_d.places import PlacesDatabase, PlacesParams
from placerec.verify.candidates import CloudStore


def test_scalar_quantiser_hand_computed_codes_and_error_bound():
    q = ScalarQuantiser.fit(np.array([[0.0, -1.0], [2.0, 3.0]]))
    # grids 0..2 and -1..3 in 255 steps, kept in faiss's layout: vmin half a step below the smallest value
    np.testing.assert_array_equal(q.vdiff, [2.0, 4.0])
    np.testing.assert_allclose(q.vmin, [-1 / 255, -1 - 2 / 255], rtol=1e-6)
    # 0.5 and 0.0 sit 63.75 steps into their grids: rounded to step 64; the ends are exact, the rest clipped
    codes = q.encode(np.array([[0.5, 0.0], [2.0, -1.0], [9.0, -7.0]]))
    np.testing.assert_array_equal(codes, [[64, 64], [255, 0], [255, 0]])
    dec = q.decode(codes)
    np.testing.assert_allclose(dec[0], [64 * 2 / 255, -1 + 64 * 4 / 255], atol=1e-6)
    np.testing.assert_allclose(dec[1], [2.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(q.max_error, [2 / 510, 4 / 510])
    x = np.random.default_rng(0).uniform([0.0, -1.0], [2.0, 3.0], size=(1000, 2)).astype(np.float32)
    err = np.abs(q.decode(q.encode(x)) - x)
    assert (err <= q.max_error + 1e-6).all() and err.max() > 0.9 * q.max_error.min()
    # a constant column still decodes to (very nearly) its value
    c = ScalarQuantiser.fit(np.full((3, 1), 0.25))
    np.testing.assert_allclose(c.decode(c.encode(np.full((1, 1), 0.25))), 0.25, atol=1e-9)


def test_faiss_decodes_the_codes_as_the_quantiser_does():
    x = np.abs(np.random.default_rng(1).normal(size=(300, 40))).astype(np.float32)
    store = DescriptorStore.from_rows(x, "sq8")
    codes = store.codes()
    assert codes.dtype == np.uint8 and codes.shape == x.shape
    np.testing.assert_array_equal(codes, store.quantiser.encode(x))
    np.testing.assert_allclose(store.rows(), store.quantiser.decode(codes), atol=1e-7)
    # faiss, which computes the search's distances, decodes the codes as the quantiser does
    np.testing.assert_allclose(store._index.reconstruct_n(0, 300), store.rows(), atol=1e-6)
    d2, _ = store._index.search(x[:3], 1)
    np.testing.assert_allclose(
        d2[:, 0],
        np.sum(
            (store.rows()[np.argmin(((store.rows()[None] - x[:3, None]) ** 2).sum(-1), 1)] - x[:3]) ** 2, 1
        ),
        rtol=1e-4,
    )
    np.testing.assert_allclose(store.take([5, 7]), store.rows()[[5, 7]])
    assert store.nbytes == 300 * 40 + 8 * 40


def test_fixed_point_cloud_and_unit_codes_hand_computed():
    f = FixedPointCloud.encode(np.array([[0.0, 0.0, 0.0], [10.0, -4.0, 2.0]]))
    np.testing.assert_array_equal(f.centre, [5.0, -2.0, 1.0])
    assert f.scale == pytest.approx(5.0 / 32767)
    np.testing.assert_array_equal(f.codes, [[-32767, 13107, -6553], [32767, -13107, 6553]])
    p = np.random.default_rng(2).uniform(-40, 40, size=(2000, 3))
    g = FixedPointCloud.encode(p)
    assert np.abs(g.decode() - p).max() <= g.scale / 2 + 4e-6  # + float32 rounding of the decoded points
    assert g.scale / 2 < 0.7e-3 and g.codes.dtype == np.int16
    np.testing.assert_array_equal(encode_unit([0.0, 0.5, 1.0, 1.5]), [0, 128, 255, 255])
    assert (
        np.abs(decode_unit(encode_unit(np.linspace(0, 1, 101))) - np.linspace(0, 1, 101)).max()
        <= 1 / 510 + 1e-7
    )


def _clusters(rng, n_centres=40, per=30, dim=64):
    centres = np.abs(rng.normal(size=(n_centres, dim)))
    rows = np.repeat(centres, per, axis=0) + 0.05 * rng.normal(size=(n_centres * per, dim))
    queries = centres + 0.02 * rng.normal(size=centres.shape)
    return rows.astype(np.float32), queries.astype(np.float32)


@pytest.mark.parametrize("dtype", ["float16", "sq8"])
def test_nearest_neighbours_on_the_compressed_store_equal_float32(dtype):
    rng = np.random.default_rng(3)
    rows, queries = _clusters(rng)
    exact = DescriptorStore.from_rows(rows)
    small = DescriptorStore.from_rows(rows, dtype)
    assert small.encoded and small.nbytes <= rows.nbytes // 2
    few, many = queries[:20], queries  # many >= BLAS_BATCH queries: the decoded-block search
    assert many.shape[0] >= BLAS_BATCH > few.shape[0]
    for q in (few, many):
        d0, i0 = exact.view().knn(q, 3)
        d1, i1 = small.view().knn(q, 3)
        same_cluster = i0 // 30 == i1 // 30
        assert same_cluster.all()
        np.testing.assert_allclose(d1, d0, rtol=0.02, atol=0.02)
    # prefix (the first 20 clusters) and mask selections: indices local to the selection, as for float32 rows
    mask = np.zeros(len(rows), bool)
    mask[::3] = True
    for view, ref in ((small.view(600), rows[:600]), (small.view(mask=mask), rows[mask])):
        for q in (few, np.concatenate([few, few])):
            d, i = view.knn2(q)
            dr, ir = DescriptorStore.from_rows(ref).view().knn2(q)
            assert (
                i[:, 0] // (30 if view.ids is None else 10) == ir[:, 0] // (30 if view.ids is None else 10)
            ).all()
            assert i.max() < len(ref)
    # the query hitting no selected row gets -1 and an infinite distance
    d, i = small.view(1).knn(queries[:2], 2)
    assert (i[:, 1] == -1).all() and np.isinf(d[:, 1]).all()


def test_sq8_store_fills_as_float32_then_fits_its_quantiser():
    rng = np.random.default_rng(4)
    rows, queries = _clusters(rng, n_centres=10, per=30)
    store = DescriptorStore(64, "sq8", fit_rows=200)
    store.append(rows[:150])
    assert not store.encoded and store.quantiser is None
    store.append(rows[150:])
    assert store.encoded and len(store) == 300
    np.testing.assert_array_equal(store.codes(), store.quantiser.encode(rows))
    with pytest.raises(ConfigError, match="unknown"):
        DescriptorStore(64, "pq")


def test_voting_on_sq8_equals_float32_on_synthetic_places():
    results = {}
    for dtype in ("float32", "sq8"):
        rec = KeypointVoting(
            features={"descriptor": "shot"}, search={"descriptor_store": dtype}, verify={"enabled": False}
        )
        descs = add_synthetic_places(rec, np.random.default_rng(5), n_places=12, per_place=40, dim=352)
        assert rec.entries.store.dtype == dtype
        queries = [d[:20] + 0.01 * np.random.default_rng(6).normal(size=d[:20].shape) for d in descs]
        results[dtype] = [
            [
                (c.match_id, c.score)
                for c in rec.query_description({"descriptors": q, "keypoints": np.zeros((20, 3))}, k=3)
            ]
            for q in queries
        ]
    assert [r[0][0] for r in results["sq8"]] == list(range(12))
    assert [[m for m, _ in r] for r in results["sq8"]] == [[m for m, _ in r] for r in results["float32"]]


@pytest.fixture(scope="module")
def compact_db():
    from placerec.artifacts.places import build_places
    from placerec.sim import SimulatedSequence
    from placerec.three_d import FeatureParams, ISSParams

    seq = SimulatedSequence("town", "vlp16", n_scans=5, seed=1, spacing=2.0, clutter=False)
    features = FeatureParams(descriptor="ishot", iss=ISSParams(max_keypoints=40))
    params = PlacesParams(
        spacing_m=4.0, window_m=0.0, features=features, descriptor_store="sq8", cloud_store="int16"
    )
    return build_places(seq, params)


def test_places_database_round_trip_keeps_the_store_and_the_search(compact_db, tmp_path):
    db = compact_db
    assert db.descriptors.dtype == "sq8" and db.descriptors.encoded
    path = tmp_path / "places.npz"
    db.save(path)
    arrays, header = load_artifact(path, "places-db", (4,))
    assert arrays["descriptors"].dtype == np.uint8 and arrays["cloud_xyz"].dtype == np.int16
    assert header["meta"]["descriptor_store"] == "sq8" and header["meta"]["cloud_store"] == "int16"
    again = PlacesDatabase.load(path)
    assert again.descriptors.dtype == "sq8"
    np.testing.assert_array_equal(again.descriptors.codes(), db.descriptors.codes())
    np.testing.assert_array_equal(again.descriptors.quantiser.vdiff, db.descriptors.quantiser.vdiff)
    q = db.descriptors.rows(0, 20) + 0.001
    for a, b in zip(db.descriptors.view().knn2(q), again.descriptors.view().knn2(q), strict=True):
        np.testing.assert_array_equal(a, b)
    for (xa, ia), (xb, ib) in zip(again.clouds, db.clouds, strict=True):
        scale = np.abs(xb - 0.5 * (xb.min(0) + xb.max(0))).max() / 32767
        assert np.abs(xa - xb).max() <= scale / 2 + 1e-5 and np.abs(ia - ib).max() <= 1 / 510 + 1e-7
    # a recognizer serves the compressed store as it is, and a float32 copy of it on request
    rec = KeypointVoting.from_places(again, verify={"cloud_store": "int16"})
    assert rec.entries.store is again.descriptors
    assert KeypointVoting.from_places(again, search={"descriptor_store": "float32"}).entries.store.dtype == (
        "float32"
    )


def test_keypoint_voting_database_round_trip_in_sq8(compact_db, tmp_path):
    rec = KeypointVoting.from_places(compact_db, verify={"enabled": False})
    assert rec.entries.store.dtype == "sq8"
    path = tmp_path / "kv.npz"
    rec.save(path)
    arrays, header = load_artifact(path, "keypoint-voting-db", (2,))
    assert arrays["descriptors"].dtype == np.uint8 and header["meta"]["descriptor_store"] == "sq8"
    back = KeypointVoting(rec.params)
    back.load(path)
    assert back.entries.store.dtype == "sq8"
    np.testing.assert_array_equal(back.entries.store.codes(), rec.entries.store.codes())
    query = {"descriptors": compact_db.descriptors.rows(0, 30) + 0.001, "keypoints": np.zeros((30, 3))}
    got = [(c.match_id, c.score) for c in back.query_description(query, k=3)]
    assert got and got == [(c.match_id, c.score) for c in rec.query_description(query, k=3)]


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda a, m: a.update(sq_vdiff=a["sq_vdiff"][:-1]), "sq_vdiff"),
        (lambda a, m: a.update(sq_vdiff=-a["sq_vdiff"]), "must be positive"),
        (lambda a, m: a.pop("sq_vmin"), "needs 'sq_vmin' and 'sq_vdiff'"),
        (lambda a, m: m.update(descriptor_store="float32"), "expected float32"),
        (lambda a, m: m.update(descriptor_store="pq"), "descriptor store 'pq' is unknown"),
        (lambda a, m: a.update(descriptors=a["descriptors"].astype(np.float16)), "expected uint8"),
        (lambda a, m: m.update(cloud_store="float32"), "float32 place clouds need"),
        (lambda a, m: a.update(cloud_intensity=a["cloud_intensity"].astype(np.float32)), "expected uint8"),
    ],
)
def test_a_corrupt_or_mismatched_quantiser_is_refused_naming_the_file(compact_db, tmp_path, change, message):
    path = tmp_path / "places.npz"
    compact_db.save(path)
    arrays, header = load_artifact(path, "places-db", (4,))
    arrays = {k: np.array(v) for k, v in arrays.items()}
    meta = dict(header["meta"])
    change(arrays, meta)
    bad = tmp_path / "bad.npz"
    save_artifact(bad, "places-db", 4, arrays, meta)
    with pytest.raises(ArtifactError, match=message) as err:
        PlacesDatabase.load(bad)
    assert str(bad) in str(err.value)


def test_packed_cloud_unpacks_to_the_same_codes_even_across_int16_wrap_around():
    from placerec.quantise import PackedCloud

    # extreme jumps between neighbouring points (the deltas wrap around int16), a single point, and none
    for p in (
        np.array([[40.0, -40.0, 0.0], [-40.0, 40.0, 1.0], [40.0, 40.0, -1.0], [-40.0, -40.0, 0.5]]),
        np.random.default_rng(3).uniform(-70, 70, size=(300, 3)),
        np.array([[1.0, 2.0, 3.0]]),
        np.zeros((0, 3)),
    ):
        f = FixedPointCloud.encode(p)
        back = PackedCloud.pack(f).unpack()
        assert back.codes.dtype == np.int16 and back.codes.shape == f.codes.shape
        np.testing.assert_array_equal(back.codes, f.codes)
        np.testing.assert_array_equal(PackedCloud.encode(p).decode(), f.decode())
        assert len(PackedCloud.encode(p)) == len(p)


def test_cloud_store_int16_halves_the_clouds_and_keeps_them_to_half_a_step():
    cloud = np.random.default_rng(7).uniform(-40, 40, size=(500, 3)).astype(np.float32)
    a, b = CloudStore(), CloudStore(dtype="int16")
    a.add(1, cloud)
    b.add(1, cloud)
    assert b.nbytes < 0.51 * a.nbytes
    assert np.abs(b.cloud(1) - a.cloud(1)).max() <= 40 / 32767
    np.testing.assert_array_equal(b.arrays([1])["cloud_counts"], [500])
    with pytest.raises(ConfigError, match="cloud store"):
        CloudStore(dtype="float8")


def test_ivf_index_over_a_compressed_store_finds_the_clusters():
    from placerec.pipelines.keypoint_voting import IvfIndex

    rows, queries = _clusters(np.random.default_rng(8))
    for dtype in ("float16", "sq8"):
        ivf = IvfIndex(DescriptorStore.from_rows(rows, dtype), nlist=8, nprobe=8)
        _, idx = ivf.knn2(queries)
        assert (idx[:, 0] // 30 == np.arange(len(queries))).all()


def test_float16_places_round_trip_and_memory_mapped_clouds_stay_mapped(compact_db, tmp_path):
    half = compact_db.stored_as("float16")
    half.save(tmp_path / "half.npz")
    back = PlacesDatabase.load(tmp_path / "half.npz", mmap=True)
    assert back.descriptors.dtype == "float16" and back.descriptors.codes().dtype == np.float16
    np.testing.assert_array_equal(back.descriptors.codes(), half.descriptors.codes())
    # a cloud that views a memory-mapped file is kept as it is (no RAM), others are encoded
    mapped = np.memmap(tmp_path / "cloud.bin", dtype=np.float32, mode="w+", shape=(50, 3))
    mapped[:] = np.random.default_rng(9).uniform(-5, 5, (50, 3))
    store = CloudStore(dtype="int16")
    store.add(1, np.asarray(mapped[:40]))
    store.add(2, np.array(mapped[:40]))
    assert store.nbytes == FixedPointCloud.encode(mapped[:40]).nbytes  # only entry 2 takes RAM
    np.testing.assert_array_equal(store.cloud(1), mapped[:40])
    # deferred clouds are made when used, and take no RAM before
    calls = []
    store.add_deferred(3, lambda: calls.append(1) or np.asarray(mapped[:10]))
    assert not calls and store.nbytes == FixedPointCloud.encode(mapped[:40]).nbytes
    np.testing.assert_array_equal(store.cloud(3), mapped[:10])
    assert calls == [1]


def test_kept_squared_norms_give_the_same_neighbours_as_computed_ones():
    """A float32 store keeps its rows' squared norms as rows are appended (`sq_norms_to`): the same values as
    computed over all rows at once, so the numpy 2-NN of a prefix view is bit for bit the one without them."""
    from placerec.retrieval.descriptor_store import knn2, sq_norms

    rng = np.random.default_rng(7)
    rows = rng.random((3000, 64), dtype=np.float32)
    store = DescriptorStore(64, "float32")
    q = rows[rng.choice(3000, 16)] + 0.01 * rng.random((16, 64), dtype=np.float32)
    for a, b in ((0, 1), (1, 700), (700, 1900), (1900, 3000)):
        store.append(rows[a:b])
        if b >= 2:  # a 2-NN needs two rows
            kept, fresh = store.view(b).knn2(q, "numpy"), knn2(q, rows[:b], "numpy")
            np.testing.assert_array_equal(kept[0], fresh[0])
            np.testing.assert_array_equal(kept[1], fresh[1])
        np.testing.assert_array_equal(store.sq_norms_to(b), sq_norms(rows[:b]))
    np.testing.assert_array_equal(store.view(1200).knn2(q, "numpy")[1], knn2(q, rows[:1200], "numpy")[1])


@pytest.mark.parametrize("dtype", ["float32", "sq8"])
def test_projected_index_finds_brute_forces_two_nearest_and_prunes_most_rows(dtype, monkeypatch):
    import placerec.retrieval.nearest as nearest
    from placerec.retrieval.nearest import ProjectedIndex

    rng = np.random.default_rng(3)
    basis = rng.normal(size=(24, 200)).astype(np.float32)
    rows = rng.normal(size=(6000, 24)).astype(np.float32) @ basis / 10 + 0.05 * rng.normal(size=(6000, 200))
    rows = rows.astype(np.float32)
    near = rows[rng.choice(6000, 40)] + 0.02 * rng.normal(size=(40, 200)).astype(np.float32)
    far = rng.normal(size=(10, 200)).astype(np.float32)  # off the rows' subspace: a loose bound
    queries = np.concatenate([near, far, rows[:2]])  # and exact duplicates of rows
    store = DescriptorStore.from_rows(rows, dtype)
    exact = knn2(queries, store.rows(), "numpy", None)
    taken, brute = [], []
    real_take = store.take
    monkeypatch.setattr(store, "take", lambda idx: taken.append(len(idx)) or real_take(idx))
    monkeypatch.setattr(nearest, "knn2", lambda *a: brute.append(1) or knn2(*a))
    # both sides expand |q - x|^2 = |q|^2 + |x|^2 - 2 q.x in float32, summed in another order: their squared
    # distances agree to the rounding of that sum (~sqrt(D) float32 steps of the norms), which the square root
    # magnifies near 0 (the exact duplicates)
    scale = float(sq_norms(store.rows()).max() + sq_norms(queries).max())
    tol = 4 * np.sqrt(rows.shape[1]) * np.finfo(np.float32).eps * scale
    pruned = {}
    for dims in (2, 32):
        idx = ProjectedIndex(store, dims=dims)
        for name, part in (("near", slice(0, 40)), ("far", slice(40, 50)), ("rows", slice(50, 52))):
            taken.clear(), brute.clear()
            dist, ind = idx.knn2(queries[part])
            assert np.array_equal(ind, exact[1][part])
            np.testing.assert_allclose(dist.astype(np.float64) ** 2, exact[0][part].astype(np.float64) ** 2,
                                       rtol=0, atol=tol)  # fmt: skip
            pruned[dims, name] = None if brute else taken[-1]  # rows read for their true distances
    # a good bound reads a small share of the rows in full; the loose ones (2 axes, queries off the rows'
    # subspace) were exact too, by pruning or by brute force
    assert pruned[32, "near"] is not None and pruned[32, "near"] < 0.1 * len(rows)
    assert pruned[32, "rows"] is not None and pruned[32, "rows"] < 0.05 * len(rows)
    # a database with no low-dimensional structure: candidates beyond half the rows, brute force instead
    noise = rng.normal(size=(500, 200)).astype(np.float32)
    brute.clear()
    d2, i2 = ProjectedIndex(noise, dims=2).knn2(noise[:5] + 0.01)
    assert brute and np.array_equal(i2[:, 0], np.arange(5))
