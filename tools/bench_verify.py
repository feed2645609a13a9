"""Benchmark the verification stage (`placerec.verify`): ms per verified candidate and pose accuracy.

Data: simulated OS1-64 pairs (``town`` world: scans 3 m apart on the route, true revisits of the route with their
nearest earlier scan, and wrong pairs ~30 m apart) and real KITTI HDL-64 pairs (odometry 00 frames 95/94 and
199/198 with ground truth; 94 vs 198 as a wrong pair; raw-drive frames k, k+5 without ground truth, compared
against a fine reference ICP). Needs ``../shared/data/real`` for the KITTI part (skipped when absent).

1. ICP backends from a perturbed ground-truth guess (0.5 m, 3 deg): small_gicp point-to-plane and GICP, Open3D
   legacy and tensor point-to-plane: ms per ICP and translation / rotation error.
2. The whole stage (`verify`, default parameters) with 300 keypoint correspondences, 70 % of them wrong: true
   keypoints are query voxels paired with their ground-truth nearest match voxel (within 0.5 m), wrong ones with a
   random match voxel (all random for wrong pairs): ms per stage, error, verified score, acceptance; and the
   accepted pose refined (``refine.enabled``, each setting of `REFINE`, the query made from its 0.4 m voxels as
   a description keeps it): the refinement's ms and error.
3. The same with real descriptor matches: Open3D FPFH on 1500 random 0.4 m voxels per scan, mutual nearest
   neighbours, ordered by feature distance; without and with the ISHOT paper's consistency grouping.
4. ICP alone (`verify_icp`, the Scan Context path) from the true yaw with no translation (wrong pairs: from the
   identity): ms, acceptance, error.
5. MapClosures (PyPI ``map-closures``) on the same pairs: the match scan is added, then the time of
   ``get_top_k_closures`` for the query (its closure search plus its RANSAC alignment) is measured.

Prints readable lines, then exactly one JSON line of headline figures.

    python tools/bench_verify.py [--sim-scans 400] [--reps 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from placerec.types import relative_pose
from placerec.verify import VerifyParams, as_source, as_target, verify, verify_icp

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
#: KITTI odometry sequences 00-02: velodyne -> camera 0 (``calib.txt`` ``Tr``), for the poses of ``poses_00.txt``.
KITTI_00_TR = np.array(
    [
        [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
        [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
        [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

BACKENDS = {
    "small_gicp plane 1.5": dict(backend="small_gicp", method="plane", source_voxel_size=1.5),
    "small_gicp plane 1.0": dict(backend="small_gicp", method="plane", source_voxel_size=1.0),
    "small_gicp gicp 1.5": dict(backend="small_gicp", method="gicp", source_voxel_size=1.5),
    "open3d plane 1.5": dict(backend="open3d", source_voxel_size=1.5),
    "open3d_t plane 1.5": dict(backend="open3d_t", source_voxel_size=1.5),
}

#: settings of `placerec.verify.params.RefineParams` measured on the accepted poses (method, query voxel m)
REFINE = {
    "gicp_0.4": {"method": "gicp", "voxel_size": 0.4},
    "gicp_1.0": {"method": "gicp", "voxel_size": 1.0},
    "gicp_1.5": {"method": "gicp", "voxel_size": 1.5},
    "plane_0.4": {"method": "plane", "voxel_size": 0.4},
}


def pose_error(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) of ``inv(T_gt) @ T_est``."""
    E = np.linalg.inv(T_gt) @ T_est
    return float(np.linalg.norm(E[:3, 3])), float(np.rad2deg(Rotation.from_matrix(E[:3, :3]).magnitude()))


def perturb(T: np.ndarray, rng: np.random.Generator, dt: float = 0.5, dr_deg: float = 3.0) -> np.ndarray:
    d = rng.normal(size=3)
    P = np.eye(4)
    P[:3, :3] = Rotation.from_rotvec(np.deg2rad(dr_deg) * d / np.linalg.norm(d)).as_matrix()
    d = rng.normal(size=3)
    P[:3, 3] = dt * d / np.linalg.norm(d)
    return P @ T


def correspondences(q_vox, m_vox, T_gt, rng, n=300, outliers=0.7, wrong_pair=False):
    """Synthetic keypoint matches on the voxelised scans (see the module docstring)."""
    q = q_vox[rng.choice(len(q_vox), size=min(4 * n, len(q_vox)), replace=False)]
    m = np.empty_like(q)
    if wrong_pair:
        return q[:n], m_vox[rng.integers(0, len(m_vox), n)]
    d, j = cKDTree(m_vox).query(q @ T_gt[:3, :3].T + T_gt[:3, 3])
    q, m = q[d < 0.5][:n], m_vox[j[d < 0.5]][:n]
    bad = rng.random(len(q)) < outliers
    m[bad] = m_vox[rng.integers(0, len(m_vox), int(bad.sum()))]
    return q, m


def fpfh_correspondences(q_xyz, m_xyz, rng, n=1500):
    """Real descriptor matches: Open3D FPFH (normals r 1 m, features r 2.5 m) on ``n`` random 0.4 m voxels of each
    scan, mutual nearest neighbours in feature space. Returns (query xyz, match xyz, feature distance)."""
    import open3d as o3d

    out = []
    for p in (q_xyz, m_xyz):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(p, dtype=np.float64)))
        pc = pc.voxel_down_sample(0.4)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=1.0, max_nn=30))
        f = o3d.pipelines.registration.compute_fpfh_feature(
            pc, o3d.geometry.KDTreeSearchParamHybrid(radius=2.5, max_nn=100)
        )
        pts, feat = np.asarray(pc.points), np.asarray(f.data).T
        keep = rng.choice(len(pts), min(n, len(pts)), replace=False)
        out.append((pts[keep], feat[keep]))
    (qp, qf), (mp, mf) = out
    d, j = cKDTree(mf).query(qf)
    _, i = cKDTree(qf).query(mf)
    mutual = i[j] == np.arange(len(qf))
    return qp[mutual], mp[j[mutual]], d[mutual]


def map_closures_ms(query: np.ndarray, match: np.ndarray, T_gt: np.ndarray | None):
    """(ms of get_top_k_closures for the query, translation error of its pose or None, inliers)."""
    from map_closures.map_closures import MapClosures

    mc = MapClosures()
    mc.get_top_k_closures(0, np.ascontiguousarray(match, dtype=np.float64), 1)
    q = np.ascontiguousarray(query, dtype=np.float64)
    t0 = time.perf_counter()
    closures = list(mc.get_top_k_closures(4, q, 1))  # ids 1-3 are its skipped recent maps
    ms = (time.perf_counter() - t0) * 1e3
    if not closures:
        return ms, None, 0
    c = closures[0]
    T_match_query = np.linalg.inv(np.asarray(c.pose, dtype=np.float64))  # its pose is T_query_match
    err = None if T_gt is None else pose_error(T_match_query, T_gt)[0]
    return ms, err, int(c.number_of_inliers)


def run_pairs(name, pairs, rng, reps, mc=True):
    """pairs: (label, query xyz, match xyz, T_gt or None, is_true). Returns rows of measurements."""
    rows = []
    default = VerifyParams()
    for label, q_xyz, m_xyz, T_gt, is_true in pairs:
        row = {"set": name, "pair": label, "true": is_true}
        ref = T_gt
        if label.startswith("raw"):  # no ground truth: the chained reference, refined by a fine GICP
            fine = VerifyParams(icp=dict(method="gicp", source_voxel_size=0.4, max_iterations=100))
            ref = verify_icp(q_xyz, m_xyz, T_gt, fine).T_match_query
        for bname, icp in BACKENDS.items():
            p = VerifyParams(icp=icp)
            src, tgt = as_source(q_xyz, p), as_target(m_xyz, p)
            ms, et, er = [], [], []
            for _ in range(reps if is_true else 1):
                v = verify_icp(src, tgt, perturb(ref, rng) if is_true else np.eye(4), p)
                ms.append(v.timings_ms["icp"])
                t, r = pose_error(v.T_match_query, ref)
                et.append(t)
                er.append(r)
            row[bname] = {
                "icp_ms": float(np.median(ms)),
                "t_err": float(np.median(et)),
                "r_err": float(np.median(er)),
                "prep_ms": src.prepare_ms + tgt.prepare_ms,
                "n_src": len(src),
                "n_tgt": len(tgt),
            }
        src, tgt = as_source(q_xyz, default), as_target(m_xyz, default)
        q_vox = as_target(q_xyz, default).points  # the query at the keypoint voxel size
        q_kp, m_kp = correspondences(q_vox, tgt.points, ref, rng, wrong_pair=not is_true)
        runs = [verify(src, tgt, q_kp, m_kp, params=default) for _ in range(reps)]
        v = runs[-1]
        stage = {k: float(np.median([r.timings_ms.get(k, 0.0) for r in runs])) for k in ("ransac", "icp")}
        per_candidate = float(
            np.median([r.timings_ms.get("ransac", 0.0) + r.timings_ms.get("icp", 0.0) for r in runs])
        )
        t_err, r_err = pose_error(v.T_match_query, ref)
        row["verify"] = {
            "ms": per_candidate,
            **{f"{k}_ms": x for k, x in stage.items()},
            "prep_ms": src.prepare_ms + tgt.prepare_ms,
            "t_err": t_err,
            "r_err": r_err,
            "score": v.score,
            "accepted": v.accepted,
            "inliers": v.inliers,
            "n_corr": len(q_kp),
            "ransac_iterations": v.ransac_iterations,
            "fitness": v.fitness,
            "rmse": v.rmse,
            "residual": v.residual,
        }
        for (
            key,
            setting,
        ) in REFINE.items():  # the accepted pose refined (the query made from its 0.4 m voxels,
            # as a description keeps it, so the refinement's ms include making its finer grid the first time)
            p = VerifyParams(refine={"enabled": True, **setting})
            v = verify(as_source(q_vox, p), tgt, q_kp, m_kp, params=p)
            t_err, r_err = pose_error(v.T_match_query, ref)
            row[f"refined_{key}"] = {
                "ms": v.timings_ms.get("refine"),
                "t_err": t_err if v.accepted else None,
                "r_err": r_err if v.accepted else None,
                "accepted": v.accepted,
            }
        yaw_only = np.eye(4)  # Scan Context's guess: the yaw, no translation (wrong pairs: the identity)
        if is_true:
            yaw = np.arctan2(ref[1, 0], ref[0, 0])
            yaw_only[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        v = verify_icp(src, tgt, yaw_only, default)
        row["icp_only"] = {
            "ms": v.timings_ms["icp"],
            "t_err": pose_error(v.T_match_query, ref)[0] if v.accepted else None,
            "accepted": v.accepted,
            "score": v.score,
        }
        fq, fm, fd = fpfh_correspondences(q_xyz, m_xyz, rng)
        true_ratio = float(np.mean(np.linalg.norm(fq @ ref[:3, :3].T + ref[:3, 3] - fm, axis=1) < 0.6))
        for key, cons in (("fpfh", False), ("fpfh_grouping", True)):
            p = VerifyParams(consistency={"enabled": cons})
            v = verify(src, tgt, fq, fm, params=p, quality=fd)
            t_err, r_err = pose_error(v.T_match_query, ref)
            row[key] = {
                "ms": v.timings_ms.get("grouping", 0.0)
                + v.timings_ms.get("ransac", 0.0)
                + v.timings_ms.get("icp", 0.0),
                "t_err": t_err if v.accepted else None,
                "accepted": v.accepted,
                "score": v.score,
                "inliers": v.inliers,
                "n_corr": len(fq),
                "true_ratio": true_ratio,
            }
        if mc:
            mc_ms, mc_err, mc_inl = map_closures_ms(q_xyz, m_xyz, ref if is_true else None)
            row["map_closures"] = {"ms": mc_ms, "t_err": mc_err, "inliers": mc_inl}
        rows.append(row)
        vv = row["verify"]
        print(
            f"{name:5s} {label:14s} true={is_true!s:5s} verify {vv['ms']:6.1f} ms (ransac {vv['ransac_ms']:.1f},"
            f" icp {vv['icp_ms']:.1f}) err {vv['t_err']:.3f} m {vv['r_err']:.2f} deg score {vv['score']:.2f}"
            f" acc={vv['accepted']!s:5s} | "
            + " | ".join(
                f"{b.split()[0][:9]}/{b.split()[1]}/{b.split()[2]} {row[b]['icp_ms']:.1f} ms {row[b]['t_err']:.3f} m"
                for b in BACKENDS
            )
            + (f" | mapclosures {row['map_closures']['ms']:.1f} ms" if mc else "")
        )
        if is_true:
            print(
                "      refined: "
                + ", ".join(
                    f"{m} {row[f'refined_{m}']['ms']:.1f} ms err {row[f'refined_{m}']['t_err']:.4f} m"
                    f" {row[f'refined_{m}']['r_err']:.3f} deg"
                    for m in REFINE
                    if row[f"refined_{m}"]["accepted"]
                )
            )
        io = row["icp_only"]
        print(
            f"      icp_only from {'yaw' if is_true else 'identity'}: {io['ms']:.1f} ms, score {io['score']:.2f},"
            f" accepted={io['accepted']}" + (f", err {io['t_err']:.3f} m" if io["t_err"] is not None else "")
        )
        for key in ("fpfh", "fpfh_grouping"):
            f = row[key]
            print(
                f"      {key:14s} {f['n_corr']} matches ({100 * f['true_ratio']:.0f} % true): {f['ms']:.1f} ms,"
                f" inliers {f['inliers']}, score {f['score']:.2f}, accepted={f['accepted']}"
                + (f", err {f['t_err']:.3f} m" if f["t_err"] is not None else "")
            )
    return rows


def sim_pairs(n_scans: int, seed: int):
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence("town", "os1-64", seed=seed, n_scans=n_scans)
    P = seq.poses
    pairs = []
    for i in (5, 40, 80, 120):
        pairs.append((f"{i + 3}->{i}", seq[i + 3].xyz, seq[i].xyz, relative_pose(P[i], P[i + 3]), True))
    for r in seq.revisits[:3]:
        qi = (r.start + r.stop) // 2
        refs = np.arange(r.ref_start, r.ref_stop)
        mi = int(refs[np.argmin(np.linalg.norm(P[refs, :3, 3] - P[qi, :3, 3], axis=1))])
        pairs.append(
            (f"{qi}->{mi} {r.kind[:3]}", seq[qi].xyz, seq[mi].xyz, relative_pose(P[mi], P[qi]), True)
        )
    for i in (10, 60, 100):
        pairs.append(
            (f"{i + 30}->{i} wrong", seq[i + 30].xyz, seq[i].xyz, relative_pose(P[i], P[i + 30]), False)
        )
    return pairs


def kitti_pairs():
    from placerec.io import read_scan
    from placerec.io.poses import read_poses

    out = []
    odo = REAL / "kitti00_frames"
    if odo.is_dir():
        cam, _ = read_poses(odo / "poses_00.txt")
        Tr, Tr_inv = KITTI_00_TR, np.linalg.inv(KITTI_00_TR)
        lidar = {i: Tr_inv @ cam[i] @ Tr for i in (94, 95, 198, 199)}
        xyz = {i: read_scan(odo / f"{i:06d}.bin").xyz for i in (94, 95, 198, 199)}
        for q, m in ((95, 94), (199, 198)):
            out.append((f"{q}->{m}", xyz[q], xyz[m], relative_pose(lidar[m], lidar[q]), True))
        out.append(("198->94 wrong", xyz[198], xyz[94], relative_pose(lidar[94], lidar[198]), False))
    raw = REAL / "kitti_raw_hdl64_sequence"
    if raw.is_dir():
        frames = [read_scan(p).xyz for p in sorted(raw.glob("*.pcd"))]
        ref = raw_reference_poses(frames)
        for k in (0, 8, 16):
            out.append(
                (f"raw {k + 5}->{k}", frames[k + 5], frames[k], np.linalg.inv(ref[k]) @ ref[k + 5], True)
            )
    return out


def raw_reference_poses(frames: list[np.ndarray]) -> list[np.ndarray]:
    """Reference poses of the raw-drive frames (no ground truth there): consecutive frames (~0.8 m apart) aligned by
    a fine GICP (all query voxels at 0.4 m, 100 iterations) from the identity, chained; then each k+5 -> k pose
    is refined the same way from the chain (done in `run_pairs` through the ``None`` ground truth)."""
    fine = VerifyParams(icp=dict(method="gicp", source_voxel_size=0.4, max_iterations=100))
    poses = [np.eye(4)]
    for a, b in zip(frames[:-1], frames[1:], strict=True):
        poses.append(poses[-1] @ verify_icp(b, a, np.eye(4), fine).T_match_query)
    return poses


def summary(rows, key, field, true=True):
    vals = [r[key][field] for r in rows if r["true"] == true and r[key][field] is not None]
    return float(np.median(vals)) if vals else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--sim-scans", type=int, default=400, help="length of the simulated sequence (revisits need ~380)"
    )
    ap.add_argument("--reps", type=int, default=3, help="perturbed starts / repeats per true pair")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-map-closures", action="store_true", help="skip the MapClosures timing")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    verify(
        np.random.default_rng(0).normal(size=(500, 3)) * 10,
        np.random.default_rng(1).normal(size=(500, 3)) * 10,
        np.eye(3) * 5,
        np.eye(3) * 5,
    )  # warm up (Numba, libraries)
    print(
        f"# bench_verify on {platform.processor() or platform.machine()}, {len(__import__('os').sched_getaffinity(0))} cores"
    )
    rows = run_pairs("sim", sim_pairs(args.sim_scans, args.seed), rng, args.reps, not args.no_map_closures)
    krows = run_pairs("kitti", kitti_pairs(), rng, args.reps, not args.no_map_closures)
    head = {"bench": "verify", "cores": len(__import__("os").sched_getaffinity(0))}
    for name, rs in (("sim", rows), ("kitti", krows)):
        if not rs:
            continue
        allr = [r["verify"]["ms"] for r in rs]
        head[f"{name}_verify_ms_median"] = float(np.median(allr))
        head[f"{name}_verify_ms_max"] = float(np.max(allr))
        head[f"{name}_ransac_ms_median"] = float(np.median([r["verify"]["ransac_ms"] for r in rs]))
        head[f"{name}_icp_ms_median"] = float(np.median([r["verify"]["icp_ms"] for r in rs]))
        head[f"{name}_prep_ms_median"] = float(np.median([r["verify"]["prep_ms"] for r in rs]))
        gt = [r for r in rs if r["true"]]
        head[f"{name}_t_err_median"] = summary(gt, "verify", "t_err")
        head[f"{name}_r_err_median"] = summary(gt, "verify", "r_err")
        head[f"{name}_true_score_min"] = float(min(r["verify"]["score"] for r in gt)) if gt else None
        wrong = [r for r in rs if not r["true"]]
        head[f"{name}_wrong_score_max"] = float(max(r["verify"]["score"] for r in wrong)) if wrong else None
        head[f"{name}_true_accepted"] = f"{sum(r['verify']['accepted'] for r in gt)}/{len(gt)}"
        head[f"{name}_wrong_accepted"] = f"{sum(r['verify']['accepted'] for r in wrong)}/{len(wrong)}"
        for b in BACKENDS:
            k = b.replace(" ", "_").replace(".", "")
            head[f"{name}_{k}_icp_ms"] = summary(gt, b, "icp_ms")
            head[f"{name}_{k}_t_err"] = summary(gt, b, "t_err")
        for m in REFINE:
            head[f"{name}_refined_{m}_t_err_median"] = summary(gt, f"refined_{m}", "t_err")
            head[f"{name}_refined_{m}_r_err_median"] = summary(gt, f"refined_{m}", "r_err")
            head[f"{name}_refined_{m}_ms_median"] = summary(gt, f"refined_{m}", "ms")
        head[f"{name}_icp_only_yaw_ms_median"] = float(np.median([r["icp_only"]["ms"] for r in gt]))
        head[f"{name}_icp_only_wrong_ms_median"] = (
            float(np.median([r["icp_only"]["ms"] for r in wrong])) if wrong else None
        )
        head[f"{name}_icp_only_true_accepted"] = f"{sum(r['icp_only']['accepted'] for r in gt)}/{len(gt)}"
        head[f"{name}_icp_only_wrong_accepted"] = (
            f"{sum(r['icp_only']['accepted'] for r in wrong)}/{len(wrong)}"
        )
        for key in ("fpfh", "fpfh_grouping"):
            head[f"{name}_{key}_ms_median"] = float(np.median([r[key]["ms"] for r in rs]))
            head[f"{name}_{key}_true_accepted"] = f"{sum(r[key]['accepted'] for r in gt)}/{len(gt)}"
            head[f"{name}_{key}_wrong_accepted"] = f"{sum(r[key]['accepted'] for r in wrong)}/{len(wrong)}"
            errs = [r[key]["t_err"] for r in gt if r[key]["t_err"] is not None]
            head[f"{name}_{key}_t_err_median"] = float(np.median(errs)) if errs else None
        if "map_closures" in rs[0]:
            head[f"{name}_map_closures_ms_median"] = float(np.median([r["map_closures"]["ms"] for r in rs]))
            errs = [r["map_closures"]["t_err"] for r in gt if r["map_closures"]["t_err"] is not None]
            head[f"{name}_map_closures_t_err_median"] = float(np.median(errs)) if errs else None
            head[f"{name}_map_closures_found"] = f"{len(errs)}/{len(gt)}"
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in head.items()}))


if __name__ == "__main__":
    main()
