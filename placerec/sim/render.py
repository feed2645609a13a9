"""Scan synthesis: cast one sweep of rays into the world (and the scan's clutter), shade the hits, measure them.

Per scan: rotate the sensor's ray grid into the world, ray-cast the static scene and the clutter mesh with Open3D
(``RaycastingScene.cast_rays``), keep the nearer hit, look up material and object of the hit triangle (ground
hits: the ground raster), evaluate the material's texture in object coordinates, apply the intensity model
(`placerec.sim.intensity`): detection / dropout, range noise, per-beam response, speckle and quantisation, and
assemble a `placerec.types.Scan` in the sensor frame. Everything is vectorised; the per-material loop runs over
the ~15 materials present, not over points.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from placerec.sim.clutter import ClutterConfig, build_clutter
from placerec.sim.geometry import MeshArrays
from placerec.sim.intensity import BeamResponse, IntensityModel, surface_response
from placerec.sim.materials import LAMBERT, P_TONE, SPECULAR, Hits, M
from placerec.sim.sensors import RayGrid, SensorModel, ray_grid
from placerec.sim.textures import shade
from placerec.sim.world import World, make_scene
from placerec.types import Scan

__all__ = ["Renderer", "RawHits"]


@dataclass
class RawHits:
    """Ray-cast result of one sweep (before shading): per ray range (inf = no hit), material, object, normal."""

    t: np.ndarray
    material: np.ndarray
    obj: np.ndarray
    normal: np.ndarray
    directions_world: np.ndarray
    clutter: MeshArrays | None = None


def _cast(scene: object, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import open3d as o3d

    res = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
    return res["t_hit"].numpy(), res["primitive_ids"].numpy(), res["primitive_normals"].numpy()


class Renderer:
    """Renders scans of one sensor in one world (holds the ray grid, beam response and intensity model)."""

    def __init__(
        self,
        world: World,
        sensor: SensorModel,
        response: BeamResponse,
        model: IntensityModel | None = None,
        clutter: ClutterConfig | None = None,
        threads: int | None = None,
    ) -> None:
        self.world = world
        self.threads = min(2, os.cpu_count() or 1) if threads is None else int(threads)
        self.sensor = sensor
        self.grid: RayGrid = ray_grid(sensor)
        self.response = response
        self.model = model or IntensityModel.for_sensor(sensor)
        self.clutter = clutter
        self._dirs_t = np.ascontiguousarray(self.grid.directions.T)

    def cast(self, pose: np.ndarray, timestamp: float, seed: int, index: int, occluders: bool = False) -> RawHits:
        """Ray-cast one sweep from ``pose`` (T_world_sensor) against the world and this scan's clutter."""
        w = self.world
        R = np.asarray(pose[:3, :3], dtype=np.float32)
        rays = np.empty((self.grid.directions.shape[0], 6), dtype=np.float32)  # per call: renders may run concurrently
        rays[:, :3] = np.asarray(pose[:3, 3], dtype=np.float32)
        rays[:, 3:] = (R @ self._dirs_t).T  # (3, N) layout: one fast GEMM
        dirs = rays[:, 3:]
        t, prim, nrm = _cast(w.scene, rays)
        valid = np.isfinite(t)
        primc = np.where(valid, prim, 0)
        mat = np.where(valid, w.tri_material[primc], M.NONE).astype(np.uint8)
        obj = np.where(valid, w.tri_object[primc], 0).astype(np.int32)
        mesh = build_clutter(w, pose, timestamp, self.clutter, seed, index, occluders)
        if mesh is not None:
            cand = self._clutter_candidates(mesh, pose, everything=occluders)
            t2, prim2, nrm2 = _cast(make_scene(mesh.vertices, mesh.triangles), rays[cand])
            closer = t2 < t[cand]
            if closer.any():
                idx = cand[closer]
                p2 = prim2[closer]
                t[idx] = t2[closer]
                mat[idx] = mesh.tri_material[p2]
                obj[idx] = mesh.tri_object[p2]
                nrm[idx] = nrm2[closer]
        return RawHits(t=t, material=mat, obj=obj, normal=nrm, directions_world=dirs, clutter=mesh)

    def _clutter_candidates(self, mesh: object, pose: np.ndarray, everything: bool) -> np.ndarray:
        """Indices of the rays that can hit the clutter: columns spanned by some clutter object, rows within the
        clutter's elevation range (all rays when near-sensor occluders may surround the sensor)."""
        n = self.grid.directions.shape[0]
        if everything:
            return np.arange(n)
        v = (np.asarray(mesh.vertices, dtype=np.float64) - pose[:3, 3]) @ pose[:3, :3]  # sensor frame
        az = np.arctan2(v[:, 1], v[:, 0])
        el = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))
        cols = self.sensor.columns
        col = np.floor((np.pi - az) / (2 * np.pi) * cols).astype(np.int64) % cols
        tri_obj = mesh.tri_object
        vobj = np.empty(len(v), np.int64)
        vobj[mesh.triangles.reshape(-1)] = np.repeat(tri_obj, 3)
        order = np.argsort(vobj, kind="stable")
        starts = np.flatnonzero(np.r_[True, vobj[order][1:] != vobj[order][:-1]])
        cmin = np.minimum.reduceat(col[order], starts)
        cmax = np.maximum.reduceat(col[order], starts)
        cover = np.zeros(cols + 1, np.int64)
        wrap = cmax - cmin > cols // 2  # object straddles column 0 / cols-1: take the whole circle (rare)
        np.add.at(cover, np.where(wrap, 0, cmin), 1)
        np.add.at(cover, np.where(wrap, cols, cmax + 1), -1)
        col_mask = np.cumsum(cover[:-1]) > 0
        margin = np.radians(1.0)
        elev = np.radians(np.asarray(self.sensor.beam_elevations_deg))
        ring_mask = (elev >= el.min() - margin) & (elev <= el.max() + margin)
        return np.flatnonzero(col_mask[self.grid.column] & ring_mask[self.grid.ring])

    def _object_table(self, m: MeshArrays | None) -> tuple[np.ndarray, np.ndarray]:
        """(M, 16) float32 rows [cos, sin, origin xyz, params...] and (M,) seeds of the world's and clutter's objects."""
        w = self.world
        if "object_table" not in w.cache:
            tab = np.zeros((w.n_objects, 16), np.float32)
            tab[:, 0] = w.obj_rot[:, 0, 0]
            tab[:, 1] = w.obj_rot[:, 0, 1]
            tab[:, 2:5] = w.obj_origin
            tab[:, 5 : 5 + w.obj_params.shape[1]] = w.obj_params
            w.cache["object_table"] = tab
        tab = w.cache["object_table"]
        if m is None or len(m.obj_seed) == 0:
            return tab, w.obj_seed
        extra = np.zeros((len(m.obj_seed), 16), np.float32)
        extra[:, 0] = m.obj_rot[:, 0, 0]
        extra[:, 1] = m.obj_rot[:, 0, 1]
        extra[:, 2:5] = m.obj_origin
        extra[:, 5 : 5 + m.obj_params.shape[1]] = m.obj_params
        return np.concatenate([tab, extra]), np.concatenate([w.obj_seed, m.obj_seed])

    def _measure_chunk(self, hits: RawHits, sel: np.ndarray, origin: np.ndarray, table: np.ndarray, oseed: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shade and measure the rays ``sel`` of one sweep: (kept ray indices, measured ranges, raw intensities)."""
        sensor = self.sensor
        t = hits.t[sel]
        d = np.take(hits.directions_world, sel, axis=0)
        pw = origin + d * t[:, None]
        mat = hits.material[sel]
        ground = mat == M.GROUND
        if ground.any():
            mat[ground] = self.world.ground.lookup(pw[ground, 0], pw[ground, 1])
        order = np.argsort(mat, kind="stable")
        sel, mat, t = sel[order], mat[order], t[order]
        d = np.take(d, order, axis=0)
        pw = np.take(pw, order, axis=0)
        obj = hits.obj[sel]
        nrm = np.take(hits.normal, sel, axis=0)
        cos_inc = np.abs(np.einsum("ij,ij->i", nrm, d))
        n = len(sel)
        # materials below FACADE (ground, paving, kerbs, ...) are textured in world coordinates and only need the
        # object's tone; the others get their hit point and normal in the object frame and the full parameters
        k0 = int(np.searchsorted(mat, M.FACADE))
        pl = np.empty((n, 3), np.float32)
        nl = np.empty((n, 3), np.float32)
        params = np.zeros((n, table.shape[1] - 5), np.float32)
        pl[:k0] = pw[:k0]
        nl[:k0] = nrm[:k0]
        params[:k0, P_TONE] = np.take(table[:, 5 + P_TONE], obj[:k0])
        if k0 < n:
            tab = np.take(table, obj[k0:], axis=0)
            c, s_ = tab[:, 0], tab[:, 1]
            dp = pw[k0:] - tab[:, 2:5]
            nr = nrm[k0:]
            pl[k0:, 0] = c * dp[:, 0] + s_ * dp[:, 1]
            pl[k0:, 1] = c * dp[:, 1] - s_ * dp[:, 0]
            pl[k0:, 2] = dp[:, 2]
            nl[k0:, 0] = c * nr[:, 0] + s_ * nr[:, 1]
            nl[k0:, 1] = c * nr[:, 1] - s_ * nr[:, 0]
            nl[k0:, 2] = nr[:, 2]
            params[k0:] = tab[:, 5:]
        seeds = np.take(oseed, obj)
        footprint = t * np.float32(sensor.beam_divergence_mrad * 1e-3) + np.float32(0.004)

        rho = np.empty(n, np.float32)
        drop = np.zeros(n, np.float32)
        depth = np.zeros(n, np.float32)
        bounds = np.searchsorted(mat, np.arange(len(M) + 1))
        for m in range(len(M)):
            a, b = bounds[m], bounds[m + 1]
            if a == b:
                continue
            sh = shade(Hits(pw[a:b], pl[a:b], nl[a:b], params[a:b], seeds[a:b], footprint[a:b], m))
            rho[a:b] = sh.reflectance
            if sh.dropout is not None:
                drop[a:b] = sh.dropout
            if sh.depth is not None:
                depth[a:b] = sh.depth

        beta = surface_response(rho, cos_inc, SPECULAR[mat], LAMBERT[mat])
        r_true = t + depth
        p_det = self.model.detection_probability(beta, r_true) * (1.0 - drop)
        keep = rng.random(n, dtype=np.float32) < p_det
        sigma = sensor.range_noise_std * (1.0 + r_true / 100.0)
        r_meas = r_true + sigma * rng.standard_normal(n, dtype=np.float32)
        keep &= (r_meas >= sensor.min_range) & (r_meas <= sensor.max_range)
        k_sel = sel[keep]
        raw = self.model.measure(beta[keep], r_true[keep], self.grid.ring[k_sel], self.response, rng)
        return k_sel, r_meas[keep], raw

    def render(self, pose: np.ndarray, timestamp: float, seed: int, index: int, occluders: bool = False, source: str | None = None) -> Scan:
        """One simulated scan (deterministic in pose, timestamp, seed and index, whatever the thread count)."""
        sensor = self.sensor
        grid = self.grid
        hits = self.cast(pose, timestamp, seed, index, occluders)
        sel = np.flatnonzero((hits.t >= sensor.min_range) & (hits.t <= sensor.max_range))
        origin = np.asarray(pose[:3, 3], dtype=np.float32)
        table, oseed = self._object_table(hits.clutter)
        # two fixed halves of the sweep, each with its own noise stream: NumPy releases the GIL in its loops, so the
        # halves shade in parallel on two cores and the result does not depend on the thread count
        N = grid.directions.shape[0]
        halves = (sel[sel < N // 2], sel[sel >= N // 2])
        rngs = [np.random.default_rng([int(seed) & 0xFFFFFFFF, int(index), 0x5CA7, k]) for k in range(2)]
        pool = _pool() if self.threads > 1 else None
        if pool is not None:
            futures = [pool.submit(self._measure_chunk, hits, h, origin, table, oseed, r) for h, r in zip(halves, rngs, strict=True)]
            parts = [f.result() for f in futures]
        else:
            parts = [self._measure_chunk(hits, h, origin, table, oseed, r) for h, r in zip(halves, rngs, strict=True)]
        k_sel = np.concatenate([p[0] for p in parts])
        r_out = np.zeros(N, np.float32)
        r_out[k_sel] = np.concatenate([p[1] for p in parts])
        xyz = grid.directions * r_out[:, None]
        inten = np.zeros(N, np.float32)
        inten[k_sel] = np.concatenate([p[2] for p in parts])
        info = sensor.to_sensor_info()
        if sensor.organized:
            return Scan(xyz=xyz, intensity=inten, ring=grid.ring.copy(), time=grid.time.copy(), shape=(sensor.n_beams, sensor.columns),
                        sensor=info, timestamp=float(timestamp), source=source)  # fmt: skip
        mask = np.zeros(N, bool)
        mask[k_sel] = True
        return Scan(xyz=xyz[mask], intensity=inten[mask], ring=grid.ring[mask], time=grid.time[mask], shape=None,
                    sensor=info, timestamp=float(timestamp), source=source)  # fmt: skip


_POOL: tuple[int, ThreadPoolExecutor] | None = None


def _pool() -> ThreadPoolExecutor:
    """A 2-thread pool for this process (recreated after a fork: threads do not survive one)."""
    global _POOL
    if _POOL is None or _POOL[0] != os.getpid():
        _POOL = (os.getpid(), ThreadPoolExecutor(max_workers=2, thread_name_prefix="placerec-sim"))
    return _POOL[1]
