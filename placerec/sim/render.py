"""Scan synthesis: cast one sweep of rays into the world (and the scan's clutter), shade the hits, measure them.

Per scan: rotate the sensor's ray grid into the world, ray-cast the static scene and the clutter mesh with Open3D
(``RaycastingScene.cast_rays``), keep the nearer hit, look up material and object of the hit triangle (ground
hits: the ground raster), evaluate the material's texture in object coordinates, apply the intensity model
(`placerec.sim.intensity`): detection / dropout, range noise, per-beam response, speckle and quantisation, and
assemble a `placerec.types.Scan` in the sensor frame. Everything after the cast runs in one compiled pass over the
hits (`_shade_rays`), on two threads (see ``docs/simulator.md#speed``).

The rays of a frame come from `placerec.sim.sensors.frame_rays`: the fixed grid of a spinning or solid-state
sensor, or the part of a non-repetitive pattern that the frame at the scan's timestamp draws. A scan taken while
moving (``pose_end``) casts each ray from the sensor pose at that ray's own time, interpolated between the frame's
start and end poses (`_sweep_rays_moving`), and reports the points in the sensor frame at their own time, as a
sensor driver delivers them (not de-skewed).
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from placerec.sim.clutter import ClutterConfig, build_clutter
from placerec.sim.geometry import MeshArrays
from placerec.sim.intensity import BeamResponse, IntensityModel, detect_and_measure_1, surface_response_1
from placerec.sim.jit import needs_compile, njit
from placerec.sim.materials import M
from placerec.sim.sensors import RayGrid, SensorModel, frame_index, frame_rays, ray_grid
from placerec.sim.site import ground_cell_1
from placerec.sim.textures import MATERIAL_TABLE, param_row, shade_hit
from placerec.sim.world import World, make_scene
from placerec.types import Scan

__all__ = ["Renderer", "RawHits"]

log = logging.getLogger(__name__)
_COMPILE_NOTED = False


@dataclass
class RawHits:
    """Ray-cast result of one sweep (before shading): per ray range (inf = no hit), material, object, normal."""

    t: np.ndarray
    material: np.ndarray
    obj: np.ndarray
    normal: np.ndarray
    rays: np.ndarray  # (N, 6) float32 [origin, unit direction] in the world frame
    clutter: MeshArrays | None = None


def _cast(scene: Any, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        _note_first_compile()
        self._model_params = self.model.packed()
        self._response_params = response.packed()
        # [beam divergence (rad), range noise sd (m), min range, max range]
        self._sensor_params = (
            sensor.beam_divergence_mrad * 1e-3,
            float(sensor.range_noise_std),
            float(sensor.min_range),
            float(sensor.max_range),
        )

    def rays_at(self, timestamp: float) -> RayGrid:
        """The rays of the frame at ``timestamp`` (the fixed grid unless the pattern is non-repetitive)."""
        if self.sensor.pattern == "non-repetitive":
            return frame_rays(self.sensor, frame_index(self.sensor, timestamp))
        return self.grid

    def cast(
        self,
        pose: np.ndarray,
        timestamp: float,
        seed: int,
        index: int,
        occluders: bool = False,
        grid: RayGrid | None = None,
        pose_end: np.ndarray | None = None,
    ) -> RawHits:
        """Ray-cast one sweep from ``pose`` (T_world_sensor) against the world and this scan's clutter.

        ``grid``: the frame's rays (default `rays_at`). ``pose_end``: the sensor pose at the end of the frame
        (``timestamp + 1 / rotation_hz``) when the sensor moves during the sweep: ray ``i`` then starts from the
        pose at its time ``time_i``, ``T(f) = (R_0 Exp(f omega), p_0 + f (p_1 - p_0))`` with ``f = time_i *
        rotation_hz`` and ``omega`` the rotation vector of ``R_0^T R_1``.
        """
        w = self.world
        grid = self.rays_at(timestamp) if grid is None else grid
        n = grid.directions.shape[0]
        rays = np.empty((n, 6), dtype=np.float32)  # per call: renders may run concurrently
        pose = np.asarray(pose, dtype=np.float64)
        if pose_end is None:
            _sweep_rays(pose, grid.directions, rays)
        else:
            omega, dp = _relative_motion(pose, np.asarray(pose_end, dtype=np.float64))
            frac = grid.time.astype(np.float64) * self.sensor.rotation_hz
            _sweep_rays_moving(pose, omega, dp, grid.directions, frac, rays)
        t, prim, nrm = _cast(w.scene, rays)
        mat = np.empty(n, np.uint8)
        obj = np.empty(n, np.int32)
        _hit_labels(t, prim, w.tri_material, w.tri_object, mat, obj)
        mesh = build_clutter(w, pose, timestamp, self.clutter, seed, index, occluders)
        if mesh is not None:
            # a moving sensor's rays do not start from ``pose``: the culling's sensor-frame angles would not hold
            cand = self._clutter_candidates(mesh, pose, grid, everything=occluders or pose_end is not None)
            t2, prim2, nrm2 = _cast(make_scene(mesh.vertices, mesh.triangles), rays[cand])
            closer = t2 < t[cand]
            if closer.any():
                idx = cand[closer]
                p2 = prim2[closer]
                t[idx] = t2[closer]
                mat[idx] = mesh.tri_material[p2]
                obj[idx] = mesh.tri_object[p2]
                nrm[idx] = nrm2[closer]
        return RawHits(t=t, material=mat, obj=obj, normal=nrm, rays=rays, clutter=mesh)

    def _clutter_candidates(
        self, mesh: MeshArrays, pose: np.ndarray, grid: RayGrid, everything: bool
    ) -> np.ndarray:
        """Indices of the rays that can hit the clutter: azimuth columns spanned by some clutter object, rays
        within the clutter's elevation range (all rays when near-sensor occluders may surround the sensor).

        Spinning sensors use their own columns and beam elevations; other patterns put every ray in one of 1440
        azimuth bins (0.25 deg) by its direction and compare its own elevation."""
        n = grid.directions.shape[0]
        if everything:
            return np.arange(n)
        v = (np.asarray(mesh.vertices, dtype=np.float64) - pose[:3, 3]) @ pose[:3, :3]  # sensor frame
        az = np.arctan2(v[:, 1], v[:, 0])
        el = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))
        spinning = self.sensor.pattern == "spinning"
        cols = self.sensor.columns if spinning else 1440
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
        if spinning:
            elev = np.radians(np.asarray(self.sensor.beam_elevations_deg))
            ring_mask = (elev >= el.min() - margin) & (elev <= el.max() + margin)
            return np.flatnonzero(col_mask[grid.column] & ring_mask[grid.ring])
        col_mask = (
            col_mask | np.roll(col_mask, 1) | np.roll(col_mask, -1)
        )  # one bin of slack for float32 rays
        d = grid.directions.astype(np.float64)
        ray_az = np.arctan2(d[:, 1], d[:, 0])
        ray_el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        ray_col = np.floor((np.pi - ray_az) / (2 * np.pi) * cols).astype(np.int64) % cols
        el_mask = (ray_el >= el.min() - margin) & (ray_el <= el.max() + margin)
        return np.flatnonzero(col_mask[ray_col] & el_mask)

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

    def _shade_half(
        self,
        hits: RawHits,
        sel: np.ndarray,
        table: np.ndarray,
        oseed: np.ndarray,
        rng: np.random.Generator,
        ring: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shade and measure the rays ``sel`` of one sweep: (kept ray indices, measured ranges, raw intensities)."""
        n = len(sel)
        u = rng.random(n, dtype=np.float32)
        z = rng.standard_normal((3, n), dtype=np.float32)
        keep = np.empty(n, np.bool_)
        r_meas = np.empty(n, np.float32)
        raw = np.empty(n, np.float32)
        ground = self.world.ground
        _shade_rays(sel, hits.t, hits.rays, hits.normal, hits.material, hits.obj, ground.labels, ground.geometry(), table, oseed,
                    ring, u, z, self._sensor_params, self._model_params, self.response.gain, self.response.gamma,
                    self.response.offset, self._response_params, MATERIAL_TABLE, keep, r_meas, raw)  # fmt: skip
        return sel[keep], r_meas[keep], raw[keep]

    def render(
        self,
        pose: np.ndarray,
        timestamp: float,
        seed: int,
        index: int,
        occluders: bool = False,
        source: str | None = None,
        pose_end: np.ndarray | None = None,
    ) -> Scan:
        """One simulated scan (deterministic in pose, timestamp, seed and index, whatever the thread count).

        ``pose_end``: the sensor pose at the end of the frame, for a scan taken while moving (see `cast`); the
        points are then in the sensor frame at their own time. ``pose`` is always the pose at ``timestamp``."""
        sensor = self.sensor
        grid = self.rays_at(timestamp)
        hits = self.cast(pose, timestamp, seed, index, occluders, grid=grid, pose_end=pose_end)
        sel = np.flatnonzero((hits.t >= sensor.min_range) & (hits.t <= sensor.max_range))
        table, oseed = self._object_table(hits.clutter)
        # two fixed halves of the sweep (even and odd ray indices, so both see the same mix of near ground and far
        # or empty sky), each with its own noise stream: the shading kernel releases the GIL, so the halves shade in
        # parallel on two cores and the result does not depend on the thread count
        N = grid.directions.shape[0]
        odd = (sel & 1).astype(bool)
        halves = (sel[~odd], sel[odd])
        rngs = [np.random.default_rng([int(seed) & 0xFFFFFFFF, int(index), 0x5CA7, k]) for k in range(2)]
        pool = _pool() if self.threads > 1 else None
        if pool is not None:
            futures = [
                pool.submit(self._shade_half, hits, h, table, oseed, r, grid.ring)
                for h, r in zip(halves, rngs, strict=True)
            ]
            parts = [f.result() for f in futures]
        else:
            parts = [
                self._shade_half(hits, h, table, oseed, r, grid.ring)
                for h, r in zip(halves, rngs, strict=True)
            ]
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


_NONE = int(M.NONE)


@njit
def _sweep_rays(pose, directions, rays):
    """Rays [origin, direction] in the world frame of the sensor-frame ``directions`` from ``pose``."""
    for i in range(directions.shape[0]):
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        for k in range(3):
            rays[i, k] = pose[k, 3]
            rays[i, 3 + k] = pose[k, 0] * dx + pose[k, 1] * dy + pose[k, 2] * dz


def _relative_motion(pose: np.ndarray, pose_end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation vector of ``R_0^T R_1`` (in the start frame), world translation ``p_1 - p_0``) over one frame."""
    from scipy.spatial.transform import Rotation

    omega = Rotation.from_matrix(pose[:3, :3].T @ pose_end[:3, :3]).as_rotvec()
    return np.ascontiguousarray(omega, dtype=np.float64), np.ascontiguousarray(pose_end[:3, 3] - pose[:3, 3])


@njit
def _sweep_rays_moving(pose, omega, dp, directions, frac, rays):
    """Rays [origin, direction] in the world frame, each from the pose at its own time: origin ``p_0 + f dp``,
    direction ``R_0 Exp(f omega) d`` (Rodrigues' formula), ``f = frac[i]`` of the frame elapsed."""
    wn = np.sqrt(omega[0] * omega[0] + omega[1] * omega[1] + omega[2] * omega[2])
    kx, ky, kz = (omega[0] / wn, omega[1] / wn, omega[2] / wn) if wn > 0 else (0.0, 0.0, 1.0)
    for i in range(directions.shape[0]):
        f = frac[i]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        th = f * wn
        c, s = np.cos(th), np.sin(th)
        kd = (kx * dx + ky * dy + kz * dz) * (1.0 - c)
        bx = dx * c + (ky * dz - kz * dy) * s + kx * kd
        by = dy * c + (kz * dx - kx * dz) * s + ky * kd
        bz = dz * c + (kx * dy - ky * dx) * s + kz * kd
        for k in range(3):
            rays[i, k] = pose[k, 3] + f * dp[k]
            rays[i, 3 + k] = pose[k, 0] * bx + pose[k, 1] * by + pose[k, 2] * bz


@njit
def _hit_labels(t, prim, tri_material, tri_object, material, obj):
    """Material and object of every hit triangle (`M.NONE` and 0 for rays that hit nothing)."""
    for i in range(t.shape[0]):
        if np.isfinite(t[i]):
            material[i] = tri_material[prim[i]]
            obj[i] = tri_object[prim[i]]
        else:
            material[i] = _NONE
            obj[i] = 0


_GROUND = int(M.GROUND)
_FACADE = int(M.FACADE)


@njit
def _shade_rays(sel, t, rays, normal, material, obj, ground_labels, ground_geometry, table, oseed, ring, u, z, sp, mp,
                gain, gamma, offset, rp, mtab, keep, r_meas, raw):  # fmt: skip
    """Shade and measure the rays ``sel`` (one pass per hit): hit point, ground material, object frame, texture,
    surface response, detection (uniform draw ``u``), range noise (``z[0]``), intensity (``z[1]``, ``z[2]``).
    ``sp`` = (beam divergence (rad), range noise sd, min range, max range); ``mp``/``rp`` = the packed
    intensity model and beam response; per-hit helpers take scalars and tuples only (no array references)."""
    for j in range(sel.shape[0]):
        i = sel[j]
        ti = t[i]
        dx, dy, dz = rays[i, 3], rays[i, 4], rays[i, 5]
        pw = (rays[i, 0] + dx * ti, rays[i, 1] + dy * ti, rays[i, 2] + dz * ti)
        nw = (normal[i, 0], normal[i, 1], normal[i, 2])
        m = material[i]
        if m == _GROUND:
            gy, gx = ground_cell_1(ground_geometry, ground_labels.shape, pw[0], pw[1])
            m = ground_labels[gy, gx]
        o = obj[i]
        prm = param_row(table, o, 5)
        if m < _FACADE:  # ground-like materials are textured in world coordinates
            pl, nl = pw, nw
        else:
            c, s = table[o, 0], table[o, 1]
            qx, qy = pw[0] - table[o, 2], pw[1] - table[o, 3]
            pl = (c * qx + s * qy, c * qy - s * qx, pw[2] - table[o, 4])
            nl = (c * nw[0] + s * nw[1], c * nw[1] - s * nw[0], nw[2])
        footprint = ti * sp[0] + 0.004
        rho, drop, depth = shade_hit(
            mtab[0, m], mtab[1, m], mtab[2, m], pw, pl, nl, prm, np.int64(oseed[o]), footprint
        )
        beta = surface_response_1(rho, abs(nw[0] * dx + nw[1] * dy + nw[2] * dz), mtab[3, m], mtab[4, m])
        r_true = ti + depth
        r = r_true + sp[1] * (1.0 + r_true / 100.0) * z[0, j]
        r_meas[j] = r
        if sp[2] <= r <= sp[3]:
            b = ring[i]
            keep[j], raw[j] = detect_and_measure_1(
                beta, r_true, 1.0 - drop, u[j], gain[b], gamma[b], offset[b], z[1, j], z[2, j], mp, rp
            )
        else:
            keep[j], raw[j] = False, 0.0


def _note_first_compile() -> None:
    """Tell the user, once per process, that the first scan waits for the shading kernel to compile."""
    global _COMPILE_NOTED
    if not _COMPILE_NOTED:
        _COMPILE_NOTED = True
        if needs_compile(_shade_rays):
            log.warning(
                "compiling the simulator's shading kernels (once after install or update, ~15 s; cached on disk)"
            )


_POOL: tuple[int, ThreadPoolExecutor] | None = None


def _pool() -> ThreadPoolExecutor:
    """A 2-thread pool for this process (recreated after a fork: threads do not survive one)."""
    global _POOL
    if _POOL is None or _POOL[0] != os.getpid():
        _POOL = (os.getpid(), ThreadPoolExecutor(max_workers=2, thread_name_prefix="placerec-sim"))
    return _POOL[1]
