"""The physical intensity model of the simulator, and the per-beam response curves kept as ground truth.

From surface to raw value, for one return at range R and incidence angle alpha:

1. **Surface response** ``beta``: Lambertian ``rho cos(alpha)`` for diffuse materials (``rho cos(alpha)^k`` with
   ``k`` 0.6-0.8 for rough ground and foliage, which backscatter more at grazing angles), plus an optional specular
   lobe ``k_s exp(-(alpha / 0.12)^2)`` (car paint, metal); retro-reflectors (``rho > 1``) follow
   ``rho cos(alpha)^0.5`` (sheeting angularity), so they stay bright at oblique angles.
2. **Received power** (LiDAR equation, VPR paper eq. 1):
   ``P ~ beta * O(R) / R^2 * exp(-2 sigma R)``, with the near-field overlap function ``O(R) = 1 - exp(-(R/R_nf)^2)``
   and atmospheric extinction ``sigma``. The return is detected with a probability that rises smoothly with
   ``P / P_min``, where ``P_min`` puts the 50 % detection range of a 10 % target at the sensor's ``range_10pct``
   (dark, far and grazing surfaces drop out, as on real sensors).
3. **Range compensation**: the sensor multiplies by ``R^2`` to report reflectance; the compensation is imperfect
   (a residual ``(R / R_ref)^-eps``) and, beyond ``degradation_range`` (~30 m, ISHOT paper Fig. 2), the low SNR
   degrades the value: ``exp(-(R - 30) / L)``, with growing noise. A sensor with ``range_compensated=False``
   reports the raw signal ``beta O(R) (R_sig / R)^2`` instead (``R_sig`` = 15 m puts the weakest detectable
   return at ~15 counts, like the MulRan OS1-64 signal channel).
4. **Speckle**: log-normal multiplicative noise, stronger beyond the degradation range.
5. **Per-beam response** (ground truth, ISHOT Fig. 7): beam ``b`` maps apparent reflectance ``x`` to
   ``S(g_b f_b(x)) + o_b`` with ``f_b(x) = x^gamma_b`` up to 1 and its tangent line ``1 + gamma_b (x - 1)`` above
   (retro-reflective range), where ``S`` is the sensor's output scale: Velodyne ``scale * x`` up to 1 (VLP-16:
   100, diffuse surfaces 0..100) and a compressive curve up to 255 for retro-reflectors, Ouster ``scale * x``
   (linear, 16 bit). The HDL-64 preset has a strongly compressive response (nominal gamma 0.5, scale 255), as the
   HDL-64E S2 of KITTI, whose asphalt reads ~0.3 of full scale.
6. **Quantisation** to integers and saturation at ``intensity_max`` (retro-reflectors saturate).

`BeamResponse.expected_raw` and `BeamResponse.to_apparent` give the noise-free curve and its inverse per beam, so
intensity calibration code can be checked against the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.sim.sensors import SensorModel

__all__ = ["BeamResponse", "IntensityModel", "surface_response"]

_RETRO_KNEE = 4.0  # Velodyne retro compression: scale + span (1 - exp(-(x - 1) / knee)), span = max + 5 - scale
_SPEC_WIDTH = 0.12  # rad


def surface_response(
    reflectance: np.ndarray, cos_incidence: np.ndarray, specular: np.ndarray | float = 0.0, lambert: np.ndarray | float = 1.0
) -> np.ndarray:
    """Effective backscatter ``beta`` of a surface (step 1 of the module docstring)."""
    rho = np.asarray(reflectance, dtype=np.float32)
    c = np.clip(np.asarray(cos_incidence, dtype=np.float32), 0.0, 1.0)
    k = np.asarray(lambert, dtype=np.float32)
    diffuse = rho * (c if np.all(k == 1.0) else c**k)
    spec = np.asarray(specular, dtype=np.float32)
    if np.any(spec > 0):
        alpha = np.arccos(c)
        diffuse = diffuse + spec * np.exp(-((alpha / _SPEC_WIDTH) ** 2))
    retro = rho > 1.0
    if np.any(retro):
        diffuse = np.where(retro, rho * np.sqrt(c), diffuse)
    return diffuse.astype(np.float32)


@dataclass(frozen=True)
class BeamResponse:
    """Per-beam nonlinear response ``raw = S(gain_b * f_b(x)) + offset_b`` (ground truth of a unit).

    ``f_b(x) = x ** gamma_b`` for ``x <= 1`` and ``1 + gamma_b (x - 1)`` above; ``S`` is the sensor's output scale.
    """

    gain: np.ndarray
    gamma: np.ndarray
    offset: np.ndarray
    family: str
    scale: float
    intensity_max: float

    @classmethod
    def draw(cls, sensor: SensorModel, seed: int) -> BeamResponse:
        """Draw a unit's curves from a seeded RNG: gains ~ lognormal(0, 0.12), gammas in [0.75, 1.3], offsets
        (Velodyne: N(0, 1.5) counts; Ouster: a positive dark level of 0.5 % + |N(0, 1.2 %)| of the scale)."""
        rng = np.random.default_rng([int(seed), 0xBEA3])
        n = sensor.n_beams
        gain = np.exp(rng.normal(0.0, 0.12, n))
        gamma = np.clip(rng.normal(1.0, 0.12, n), 0.75, 1.3) * sensor.response_gamma
        if sensor.family == "velodyne":
            offset = rng.normal(0.0, 1.5, n)
        else:  # a dark level: a 16-bit channel does not report detected returns at zero
            offset = np.abs(rng.normal(0.0, 0.012 * sensor.intensity_scale, n)) + 0.005 * sensor.intensity_scale
        return cls(
            gain=gain.astype(np.float64),
            gamma=gamma.astype(np.float64),
            offset=offset.astype(np.float64),
            family=sensor.family,
            scale=float(sensor.intensity_scale),
            intensity_max=sensor.intensity_max,
        )

    @property
    def n_beams(self) -> int:
        return int(self.gain.shape[0])

    def _scale_out(self, y: np.ndarray) -> np.ndarray:
        if self.family == "velodyne":
            span = self.intensity_max + 5.0 - self.scale
            retro = self.scale + span * (1.0 - np.exp(-(np.maximum(y, 1.0) - 1.0) / _RETRO_KNEE))
            return np.where(y <= 1.0, self.scale * y, retro)
        return self.scale * y

    def _scale_in(self, raw: np.ndarray) -> np.ndarray:
        if self.family == "velodyne":
            span = self.intensity_max + 5.0 - self.scale
            frac = np.clip((raw - self.scale) / span, 0.0, 1.0 - 1e-9)
            retro = 1.0 - _RETRO_KNEE * np.log1p(-frac)
            return np.where(raw <= self.scale, raw / self.scale, retro)
        return raw / self.scale

    def expected_raw(self, apparent: np.ndarray, beam: np.ndarray | int, clip: bool = True) -> np.ndarray:
        """Noise-free, unquantised raw value of beam(s) ``beam`` for apparent reflectance ``apparent``.

        ``apparent`` is the range-compensated surface response (`IntensityModel.apparent`); for a Lambertian
        surface at normal incidence within the compensated range it is close to the true reflectance.
        """
        x = np.maximum(np.asarray(apparent), 0.0)
        b = np.asarray(beam)
        g = self.gamma[b].astype(x.dtype, copy=False)
        y = self.gain[b].astype(x.dtype, copy=False) * np.where(x <= 1.0, x**g, 1.0 + g * (x - 1.0))
        raw = self._scale_out(y) + self.offset[b].astype(x.dtype, copy=False)
        return np.clip(raw, 0.0, self.intensity_max) if clip else raw

    def to_apparent(self, raw: np.ndarray, beam: np.ndarray | int) -> np.ndarray:
        """Inverse of `expected_raw` (saturated values map to the lower bound of what could saturate)."""
        r = np.asarray(raw, dtype=np.float64)
        b = np.asarray(beam)
        z = np.maximum(self._scale_in(r - self.offset[b]), 0.0) / self.gain[b]
        g = self.gamma[b]
        return np.where(z <= 1.0, z ** (1.0 / g), 1.0 + (z - 1.0) / g)


@dataclass(frozen=True)
class IntensityModel:
    """Range, noise and detection part of the intensity model for one sensor (see the module docstring)."""

    range_10pct: float
    range_compensated: bool = True
    reference_range: float = 10.0
    near_field_range: float = 1.2
    residual_exponent: float = 0.1
    degradation_range: float = 30.0
    degradation_length: float = 40.0
    extinction: float = 1e-4
    speckle: float = 0.10
    speckle_far: float = 0.30
    detection_softness: float = 0.25
    signal_range: float = 15.0

    @classmethod
    def for_sensor(cls, sensor: SensorModel) -> IntensityModel:
        return cls(
            range_10pct=sensor.range_10pct,
            range_compensated=sensor.range_compensated,
            degradation_range=sensor.degradation_range,
        )

    def received_power(self, beta: np.ndarray, rng_m: np.ndarray) -> np.ndarray:
        """Relative received power ``beta O(R) exp(-2 sigma R) / R^2`` (LiDAR equation)."""
        r = np.maximum(np.asarray(rng_m, dtype=np.float32), 1e-3)
        overlap = 1.0 - np.exp(-((r / self.near_field_range) ** 2))
        return np.asarray(beta, dtype=np.float32) * overlap * np.exp(-2.0 * self.extinction * r) / (r * r)

    def detection_probability(self, beta: np.ndarray, rng_m: np.ndarray) -> np.ndarray:
        """Probability that a return is detected at all (a logistic in log received power)."""
        p_min = 0.1 * np.exp(-2.0 * self.extinction * self.range_10pct) / self.range_10pct**2
        p = self.received_power(beta, rng_m)
        z = np.log(np.maximum(p, 1e-30) / p_min) / self.detection_softness
        return 1.0 / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))

    def range_factor(self, rng_m: np.ndarray) -> np.ndarray:
        """Multiplier from surface response to apparent reflectance, as a function of range."""
        r = np.maximum(np.asarray(rng_m, dtype=np.float32), 1e-3)
        overlap = 1.0 - np.exp(-((r / self.near_field_range) ** 2))
        atm = np.exp(-2.0 * self.extinction * r)
        if not self.range_compensated:
            return overlap * atm * (self.signal_range / r) ** 2
        residual = (r / self.reference_range) ** (-self.residual_exponent)
        degrade = np.exp(-np.maximum(r - self.degradation_range, 0.0) / self.degradation_length)
        return overlap * atm * residual * degrade

    def apparent(self, beta: np.ndarray, rng_m: np.ndarray) -> np.ndarray:
        """Noise-free apparent reflectance the sensor reports before its per-beam response."""
        return np.asarray(beta, dtype=np.float32) * self.range_factor(rng_m)

    def speckle_sigma(self, rng_m: np.ndarray) -> np.ndarray:
        far = np.clip((np.asarray(rng_m, dtype=np.float32) - self.degradation_range) / self.degradation_range, 0, 1.5)
        return self.speckle + self.speckle_far * far

    def measure(
        self,
        beta: np.ndarray,
        rng_m: np.ndarray,
        beam: np.ndarray,
        response: BeamResponse,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """Noisy, quantised raw intensity (float32 integers in [0, intensity_max])."""
        x = self.apparent(beta, rng_m)
        s = self.speckle_sigma(rng_m)
        x = x * np.exp(s * rng.standard_normal(x.shape[0], dtype=np.float32) - 0.5 * s * s)
        raw = response.expected_raw(x, beam, clip=False)
        add_sd = 0.6 if response.family == "velodyne" else 0.004 * response.scale
        raw = raw + add_sd * rng.standard_normal(raw.shape[0], dtype=np.float32)
        return np.clip(np.rint(raw), 0.0, response.intensity_max).astype(np.float32)
