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
   (linear, 16 bit). Livox's 8-bit reflectivity has the same two-part form with scale 150 (0..150 diffuse for
   0..100 % reflectance, 151..255 retro-reflective, as the Livox SDK documents it), and the RoboSense preset uses
   Velodyne's 0..100 / 101..255 split (an assumption: the E1R's intensity mapping is not published). These
   8-bit families are called piecewise below; the response curves have one entry per beam, laser line (Livox) or
   raster row (solid state). The HDL-64 preset has a strongly compressive response (nominal gamma 0.5, scale
   255), as the HDL-64E S2 of KITTI, whose asphalt reads ~0.3 of full scale.
6. **Quantisation** to integers and saturation at ``intensity_max`` (retro-reflectors saturate).

`BeamResponse.expected_raw` and `BeamResponse.to_apparent` give the noise-free curve and its inverse per beam, so
intensity calibration code can be checked against the truth.

Each step is one scalar kernel (``*_1``, compiled with Numba) that the renderer calls per hit; the NumPy-style
functions and methods here run the same kernels over arrays, so there is one implementation of every formula.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.sim.jit import elementwise, inline, njit
from placerec.sim.sensors import SensorModel

__all__ = ["BeamResponse", "IntensityModel", "surface_response"]

# Velodyne retro compression: scale + span (1 - exp(-(x - 1) / knee)), span = max + 5 - scale
_RETRO_KNEE = 4.0
# 8-bit families with a diffuse range up to ``scale`` and a compressive retro-reflective range above it
PIECEWISE_FAMILIES = ("velodyne", "livox", "robosense")
_SPEC_WIDTH = 0.12  # rad
_F4 = np.float32
_F8 = np.float64
_I8 = np.int64

# indices into `IntensityModel.packed()` and `BeamResponse.packed()`
(_RANGE_10, _COMPENSATED, _REF_RANGE, _NEAR_FIELD, _RESIDUAL, _DEGRADE_AT, _DEGRADE_LEN, _EXTINCTION, _SPECKLE,
 _SPECKLE_FAR, _SOFTNESS, _SIGNAL_RANGE, _P_MIN) = range(13)  # fmt: skip
_VELODYNE, _SCALE, _MAX, _ADD_SD = range(4)
_E_50 = float(np.exp(50.0))
_E_M50 = float(np.exp(-50.0))


# -- scalar kernels (one hit) ---------------------------------------------------------------------------------------
@inline
def surface_response_1(rho: float, cos_incidence: float, specular: float, lambert: float) -> float:
    """Effective backscatter ``beta`` of one surface point (step 1 of the module docstring)."""
    c = min(max(cos_incidence, 0.0), 1.0)
    if rho > 1.0:
        return rho * np.sqrt(c)  # retro-reflective sheeting
    beta = rho * (c if lambert == 1.0 else c**lambert)
    if specular > 0:
        beta += specular * np.exp(-((np.arccos(c) / _SPEC_WIDTH) ** 2))
    return beta


@inline
def path_gain_1(rng_m: float, mp: tuple) -> float:
    """Near-field overlap times two-way atmospheric transmission, ``O(R) exp(-2 sigma R)``, at range ``rng_m``."""
    r = max(rng_m, 1e-3)
    q = r / mp[_NEAR_FIELD]
    overlap = 1.0 - np.exp(-q * q) if q < 6.5 else 1.0  # beyond 6.5 R_nf the overlap is 1 within 1e-18
    return overlap * np.exp(-2.0 * mp[_EXTINCTION] * r)


@inline
def received_power_1(beta: float, rng_m: float, mp: tuple) -> float:
    """Relative received power ``beta O(R) exp(-2 sigma R) / R^2`` (LiDAR equation)."""
    r = max(rng_m, 1e-3)
    return beta * path_gain_1(r, mp) / (r * r)


@inline
def _detection_from_power(power: float, mp: tuple) -> float:
    # the logistic 1 / (1 + exp(-z)) of z = ln(P / P_min) / softness, as 1 / (1 + (P / P_min) ** (-1 / softness)),
    # with z clipped to [-50, 50]
    q = max(power, 1e-30) / mp[_P_MIN]
    return 1.0 / (1.0 + min(max(q ** (-1.0 / mp[_SOFTNESS]), _E_M50), _E_50))


@inline
def detection_probability_1(beta: float, rng_m: float, mp: tuple) -> float:
    """Probability that a return is detected at all (a logistic in log received power)."""
    return _detection_from_power(received_power_1(beta, rng_m, mp), mp)


@inline
def _range_factor_from_gain(rng_m: float, gain: float, mp: tuple) -> float:
    r = max(rng_m, 1e-3)
    if mp[_COMPENSATED] == 0:
        return gain * (mp[_SIGNAL_RANGE] / r) ** 2
    f = gain * (r / mp[_REF_RANGE]) ** (-mp[_RESIDUAL])
    if r > mp[_DEGRADE_AT]:
        f *= np.exp(-(r - mp[_DEGRADE_AT]) / mp[_DEGRADE_LEN])
    return f


@inline
def range_factor_1(rng_m: float, mp: tuple) -> float:
    """Multiplier from surface response to apparent reflectance at range ``rng_m``."""
    return _range_factor_from_gain(rng_m, path_gain_1(rng_m, mp), mp)


@inline
def speckle_sigma_1(rng_m: float, mp: tuple) -> float:
    far = min(max((rng_m - mp[_DEGRADE_AT]) / mp[_DEGRADE_AT], 0.0), 1.5)
    return mp[_SPECKLE] + mp[_SPECKLE_FAR] * far


@inline
def expected_raw_1(apparent: float, gain: float, gamma: float, offset: float, rp: tuple) -> float:
    """Noise-free, unquantised, unclipped raw value of a beam with curve (gain, gamma, offset) for apparent
    reflectance ``apparent`` (``rp`` = `BeamResponse.packed`)."""
    x = max(apparent, 0.0)
    y = gain * (x**gamma if x <= 1.0 else 1.0 + gamma * (x - 1.0))
    scale = rp[_SCALE]
    if rp[_VELODYNE] != 0 and y > 1.0:
        span = rp[_MAX] + 5.0 - scale
        out = scale + span * (1.0 - np.exp(-(y - 1.0) / _RETRO_KNEE))
    else:
        out = scale * y
    return out + offset


@inline
def _measure_from_factor(beta, rng_m, factor, gain, gamma, offset, z_speckle, z_noise, mp, rp) -> float:
    s = speckle_sigma_1(rng_m, mp)
    x = beta * factor * np.exp(s * z_speckle - 0.5 * s * s)
    raw = expected_raw_1(x, gain, gamma, offset, rp) + rp[_ADD_SD] * z_noise
    return min(max(np.rint(raw), 0.0), rp[_MAX])


@inline
def measure_1(beta: float, rng_m: float, gain: float, gamma: float, offset: float, z_speckle: float, z_noise: float,
              mp: tuple, rp: tuple) -> float:  # fmt: skip
    """Noisy, quantised raw intensity of one return on a beam with curve (gain, gamma, offset), given two
    standard-normal draws (speckle, additive noise)."""
    factor = range_factor_1(rng_m, mp)
    return _measure_from_factor(beta, rng_m, factor, gain, gamma, offset, z_speckle, z_noise, mp, rp)


@inline
def detect_and_measure_1(beta: float, rng_m: float, p_pass: float, u: float, gain: float, gamma: float,
                         offset: float, z_speckle: float, z_noise: float, mp: tuple, rp: tuple) -> tuple[bool, float]:  # fmt: skip
    """`detection_probability_1` (times ``p_pass``, the chance the beam is not lost on the way) decided by the
    uniform draw ``u``, then `measure_1` of a detected return: (detected?, raw intensity or 0). Shares the path
    gain between the two steps."""
    r = max(rng_m, 1e-3)
    g = path_gain_1(r, mp)
    if u >= _detection_from_power(beta * g / (r * r), mp) * p_pass:
        return False, 0.0
    factor = _range_factor_from_gain(r, g, mp)
    return True, _measure_from_factor(beta, rng_m, factor, gain, gamma, offset, z_speckle, z_noise, mp, rp)


# -- array kernels --------------------------------------------------------------------------------------------------
@njit
def _surface_response_n(rho, c, spec, k, out):
    for i in range(out.shape[0]):
        out[i] = surface_response_1(rho[i], c[i], spec[i], k[i])


@njit
def _received_power_n(beta, r, mp, out):
    for i in range(out.shape[0]):
        out[i] = received_power_1(beta[i], r[i], mp)


@njit
def _detection_probability_n(beta, r, mp, out):
    for i in range(out.shape[0]):
        out[i] = detection_probability_1(beta[i], r[i], mp)


@njit
def _apparent_n(beta, r, mp, out):
    for i in range(out.shape[0]):
        out[i] = beta[i] * range_factor_1(r[i], mp)


@njit
def _speckle_sigma_n(r, mp, out):
    for i in range(out.shape[0]):
        out[i] = speckle_sigma_1(r[i], mp)


@njit
def _expected_raw_n(x, beam, gain, gamma, offset, rp, out):
    for i in range(out.shape[0]):
        b = beam[i]
        out[i] = expected_raw_1(x[i], gain[b], gamma[b], offset[b], rp)


@njit
def _measure_n(beta, r, beam, z1, z2, mp, gain, gamma, offset, rp, out):
    for i in range(out.shape[0]):
        b = beam[i]
        out[i] = measure_1(beta[i], r[i], gain[b], gamma[b], offset[b], z1[i], z2[i], mp, rp)


def surface_response(
    reflectance: np.ndarray,
    cos_incidence: np.ndarray,
    specular: np.ndarray | float = 0.0,
    lambert: np.ndarray | float = 1.0,
) -> np.ndarray:
    """Effective backscatter ``beta`` of a surface (step 1 of the module docstring), float32."""
    return elementwise(
        _surface_response_n, (reflectance, cos_incidence, specular, lambert), (_F4,) * 4, np.float32
    )


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
        if sensor.family in PIECEWISE_FAMILIES:
            offset = rng.normal(0.0, 1.5, n)
        else:  # a dark level: a 16-bit channel does not report detected returns at zero
            offset = (
                np.abs(rng.normal(0.0, 0.012 * sensor.intensity_scale, n)) + 0.005 * sensor.intensity_scale
            )
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

    def packed(self) -> tuple[float, ...]:
        """(velodyne?, scale, intensity_max, additive noise sd) for the compiled kernels."""
        velodyne = self.family in PIECEWISE_FAMILIES
        return (
            float(velodyne),
            float(self.scale),
            float(self.intensity_max),
            0.6 if velodyne else 0.004 * self.scale,
        )

    def _scale_in(self, raw: np.ndarray) -> np.ndarray:
        if self.family in PIECEWISE_FAMILIES:
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
        x = np.asarray(apparent)
        dtype = x.dtype if x.dtype.kind == "f" else np.float64
        raw = elementwise(
            _expected_raw_n, (x, beam), (_F8, _I8), dtype, self.gain, self.gamma, self.offset, self.packed()
        )
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

    def packed(self) -> tuple[float, ...]:
        """The parameters as the tuple of floats the compiled kernels read (the detection threshold ``P_min``
        last: the received power of a 10 % target at ``range_10pct``)."""
        p_min = 0.1 * np.exp(-2.0 * self.extinction * self.range_10pct) / self.range_10pct**2
        values = (self.range_10pct, self.range_compensated, self.reference_range, self.near_field_range,
                  self.residual_exponent, self.degradation_range, self.degradation_length, self.extinction,
                  self.speckle, self.speckle_far, self.detection_softness, self.signal_range, p_min)  # fmt: skip
        return tuple(float(v) for v in values)

    def received_power(self, beta: np.ndarray, rng_m: np.ndarray) -> np.ndarray:
        """Relative received power ``beta O(R) exp(-2 sigma R) / R^2`` (LiDAR equation)."""
        return elementwise(_received_power_n, (beta, rng_m), (_F4, _F4), np.float32, self.packed())

    def detection_probability(self, beta: np.ndarray, rng_m: np.ndarray) -> np.ndarray:
        """Probability that a return is detected at all (a logistic in log received power)."""
        return elementwise(_detection_probability_n, (beta, rng_m), (_F4, _F4), np.float32, self.packed())

    def range_factor(self, rng_m: np.ndarray) -> np.ndarray:
        """Multiplier from surface response to apparent reflectance, as a function of range."""
        return self.apparent(1.0, rng_m)

    def apparent(self, beta: np.ndarray | float, rng_m: np.ndarray) -> np.ndarray:
        """Noise-free apparent reflectance the sensor reports before its per-beam response."""
        return elementwise(_apparent_n, (beta, rng_m), (_F4, _F4), np.float32, self.packed())

    def speckle_sigma(self, rng_m: np.ndarray) -> np.ndarray:
        return elementwise(_speckle_sigma_n, (rng_m,), (_F4,), np.float32, self.packed())

    def measure(
        self,
        beta: np.ndarray,
        rng_m: np.ndarray,
        beam: np.ndarray,
        response: BeamResponse,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """Noisy, quantised raw intensity (float32 integers in [0, intensity_max])."""
        n = np.broadcast_shapes(np.shape(beta), np.shape(rng_m), np.shape(beam))
        z_speckle = rng.standard_normal(n, dtype=np.float32)
        z_noise = rng.standard_normal(n, dtype=np.float32)
        return elementwise(_measure_n, (beta, rng_m, beam, z_speckle, z_noise), (_F4, _F4, _I8, _F4, _F4), np.float32,
                           self.packed(), response.gain, response.gamma, response.offset, response.packed())  # fmt: skip
