"""Scan patterns of LiDARs that are not one 360 deg spinning sweep: Risley-prism rosettes and solid-state rasters.

Every generator returns, for one frame, unit ray directions in the sensor frame (x forward, y left, z up), each
ray's line / row index and its time since the frame start, in firing order (times non-decreasing).

**Risley rosette** (Livox Avia, Mid-40/70, Horizon): the lasers shine through two wedge prisms that rotate about
the optical axis at different rates. To first order (thin prisms, paraxial) each prism deflects the beam by a
fixed angle ``delta_k = (n - 1) alpha_k`` in the direction of its wedge, so the deflection is the **sum of two
rotating vectors** ``d(t) = delta_1 e(2 pi f_1 t + phi_1) + delta_2 e(2 pi f_2 t + phi_2)`` (``e(a) = (cos a,
sin a)``). With counter-rotating prisms (``f_1 f_2 < 0``) and equal deflections the beam draws a rose (petals
through the centre) whose orientation precesses at ``(f_1 + f_2) / 2``; when ``f_1 / f_2`` is irrational the
curve never closes, so the covered part of the field of view keeps growing with integration time — the property
Livox calls non-repetitive scanning. Each laser line ``i`` enters the prisms at a fixed offset ``o_i`` in the
focal plane, so it draws the same rose shifted by ``o_i``. Offsets and deflections are normalised so that the
pattern fills the ellipse ``(az / half_h)^2 + (el / half_v)^2 <= 1``: the rays never leave the field of view.

**Spinning-wedge pattern** (Livox MID-360): a rotor carries the lines around the vertical axis while a wedge
prism on it rotates at an incommensurate rate, adding a small rotating deflection to each line's azimuth and
elevation. Line ``i`` sweeps the band ``e_i +- delta`` of elevation; the bands tile the vertical field of view.
Because the two rates are incommensurate, each revolution lays the wiggle at a new phase, and the band fills in
over time.

**Solid-state raster** (RoboSense E1R-like): a fixed ``rows x cols`` grid of directions, the same every frame,
read out row by row (top row first; the columns of a row share a time stamp).

The prism and rotor rates of the Livox sensors are not published; the values in `placerec.sim.sensors` are
assumptions chosen so that one 0.1 s frame shows a rosette with gaps that fill in over about a second, as in
Livox's published coverage-versus-integration-time plots.
"""

from __future__ import annotations

import numpy as np

__all__ = ["rosette_rays", "spinning_wedge_rays", "raster_rays", "directions_from_angles"]


def directions_from_angles(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """(N, 3) float32 unit vectors of azimuth ``az`` (from +x towards +y) and elevation ``el`` (radians)."""
    ce = np.cos(el)
    d = np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=-1)
    return np.ascontiguousarray(d, dtype=np.float32)


def _pulse_times(n_pulses: int, lines: int, point_rate: float, t0: float) -> tuple[np.ndarray, np.ndarray]:
    """Absolute pulse times ``t0 + j / (point_rate / lines)`` (all lines fire together) and times in the frame."""
    j = np.arange(n_pulses, dtype=np.float64)
    rel = j * (lines / point_rate)
    return t0 + rel, rel


def rosette_rays(
    half_h_deg: float,
    half_v_deg: float,
    point_rate: float,
    frame_s: float,
    t0: float,
    prism_hz: tuple[float, float],
    line_offsets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of a Risley-prism rosette over ``[t0, t0 + frame_s)``: (directions, line, time since ``t0``).

    ``line_offsets`` (L, 2) are the lines' focal-plane offsets in units of the half field of view (|o| < 1); the
    two prisms deflect by ``(1 - max|o|) / 2`` each, so every ray stays within the elliptical field of view.
    Pulses are emitted at ``point_rate / L`` per line, all lines together; the output is pulse-major.
    """
    offs = np.asarray(line_offsets, dtype=np.float64).reshape(-1, 2)
    lines = offs.shape[0]
    n_pulses = int(round(point_rate * frame_s / lines))
    t_abs, rel = _pulse_times(n_pulses, lines, point_rate, t0)
    a = 0.5 * (1.0 - float(np.max(np.hypot(offs[:, 0], offs[:, 1]))))
    ph1 = 2.0 * np.pi * np.mod(prism_hz[0] * t_abs, 1.0)  # mod before scaling: exact phase at large t
    ph2 = 2.0 * np.pi * np.mod(prism_hz[1] * t_abs, 1.0) + 0.5 * np.pi
    dx = a * (np.cos(ph1) + np.cos(ph2))
    dy = a * (np.sin(ph1) + np.sin(ph2))
    ux = dx[:, None] + offs[None, :, 0]  # (pulse, line)
    uy = dy[:, None] + offs[None, :, 1]
    az = np.radians(half_h_deg) * ux.reshape(-1)
    el = np.radians(half_v_deg) * uy.reshape(-1)
    line = np.tile(np.arange(lines, dtype=np.int16), n_pulses)
    time = np.repeat(rel, lines).astype(np.float32)
    return directions_from_angles(az, el), line, time


def spinning_wedge_rays(
    elev_up_deg: float,
    elev_down_deg: float,
    lines: int,
    point_rate: float,
    frame_s: float,
    t0: float,
    rotor_hz: float,
    wedge_hz: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of a rotor-plus-wedge scanner (360 deg) over ``[t0, t0 + frame_s)``: (directions, line, time).

    Line ``i`` (0 = top) is centred on ``e_i`` with bands of half-width ``delta = (up + down) / (2 L)`` that tile
    ``[-down, +up]``; the wedge adds ``delta (sin w, cos w)`` to (azimuth, elevation), with line ``i``'s wedge
    phase shifted by ``2 pi i / L`` (the lines pass through the prism at different places).
    """
    n_pulses = int(round(point_rate * frame_s / lines))
    t_abs, rel = _pulse_times(n_pulses, lines, point_rate, t0)
    delta = np.radians(elev_up_deg + elev_down_deg) / (2.0 * lines)
    centres = np.radians(elev_up_deg) - delta * (1.0 + 2.0 * np.arange(lines))
    rotor = 2.0 * np.pi * np.mod(rotor_hz * t_abs, 1.0)
    w = 2.0 * np.pi * np.mod(wedge_hz * t_abs, 1.0)
    w = w[:, None] + 2.0 * np.pi * np.arange(lines)[None, :] / lines
    # the deflection is scaled a hair below delta so rounding cannot push a ray past the field of view
    az = (rotor[:, None] + 0.999 * delta * np.sin(w)).reshape(-1)
    el = (centres[None, :] + 0.999 * delta * np.cos(w)).reshape(-1)
    line = np.tile(np.arange(lines, dtype=np.int16), n_pulses)
    time = np.repeat(rel, lines).astype(np.float32)
    return directions_from_angles(az, el), line, time


def raster_rays(
    h_fov_deg: float, elev_up_deg: float, elev_down_deg: float, rows: int, cols: int, frame_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A solid-state raster: (directions, row, column, time), row-major, top row first, column 0 on the left.

    Pixel centres: azimuth ``+h/2 - h (c + 0.5) / cols`` (decreasing with the column, as the spinning presets),
    elevation ``up - (up + down) (r + 0.5) / rows``; row ``r`` is read out at ``r frame_s / rows``.
    """
    az = np.radians(0.5 * h_fov_deg - h_fov_deg * (np.arange(cols) + 0.5) / cols)
    el = np.radians(elev_up_deg - (elev_up_deg + elev_down_deg) * (np.arange(rows) + 0.5) / rows)
    E, A = np.meshgrid(el, az, indexing="ij")
    R, C = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    time = (R.reshape(-1) * (frame_s / rows)).astype(np.float32)
    return (
        directions_from_angles(A.reshape(-1), E.reshape(-1)),
        R.reshape(-1).astype(np.int16),
        C.reshape(-1).astype(np.int32),
        time,
    )
