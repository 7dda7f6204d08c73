"""Simulated encoder recordings with known truth (patent seed 000): one or more diode arrays on one code disk.

:class:`EncoderScenario` holds the truth as attributes -- edge angles with their graduation errors, the disk
positions, each array's geometry, aperture, dark level, illumination per frame, per-diode gain -- and gives
``exact_measurements()`` (the frame model of :mod:`selfcal.models.encoder`, noise-free),
``perturbed_measurements(seed)`` (plus white noise, clipped at the ADC range) and ``truth()`` (a YAML-ready dict,
written to ``truth/`` and never read by estimators).

Truth conventions
-----------------
* Edge ``e`` is at ``alpha_e = 2 pi k_e / m + g_e``; the graduation errors ``g`` are a few low harmonics
  (amplitude ``harmonic_rad`` each, random phase) plus independent per-edge errors (``random_rad``), shifted so
  that ``g_0 = 0``: the same gauge the calibration uses (edge 0 at its nominal angle), so estimated and true
  angles compare directly.
* Array ``k`` sees the disk at ``beta + offset_k`` (array 0: offset 0).  Eccentricity ``epsilon`` (code centre
  off the axis, in code radii) enters every array as ``u = epsilon sin(gamma) h/c_y``... (the reduction of
  :class:`selfcal.models.encoder.PhysicalGeometry`); for the standard layout (source and array at the code
  radius R, array tangential) ``h / c_y = -1/R`` and ``u = -eps_y``, ``v = eps_x`` with ``eps`` in radii.
* Temperature: ``p_J = p (1 + scale_per_degC (T_J - T_ref))`` (the optional drift), with ``T`` in the
  ``temperature [degC]`` column.
* Light intensity: the illumination profile times ``1 + intensity_drift`` per frame (random, per frame).
* Slow drift (durable self-calibration, a long run of ordinary measurements): with the temperature
  ``dT_J = T_J - T_ref``, the dark level ``a0_J = a0 + a0_per_degC dT_J`` (dark current, ADC offset), the
  aperture ``(t-, t+)_J = (t-, t+) (1 + aperture_per_degC dT_J)`` (the shadow's blur grows with the disk-array
  gap) and the light ``(1 + intensity_per_degC dT_J)`` (an LED dims as it warms), next to ``p_J`` above.
  ``temperature_profile="ramp"`` runs the temperature from ``T_ref`` to ``T_ref + temperature_range_degC``
  (a run that starts where its calibration was made); ``"centred"`` (default) sweeps it about ``T_ref``.
  Edges do not drift: a disk's uniform expansion leaves its angles unchanged.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from selfcal.io.recording import Recording, SensorData, to_plain, write_recording
from selfcal.models import encoder as enc

T0_NS = 1_700_000_000 * 10**9
TEMPERATURE_REF_DEGC = 25.0


def nominal_p(code: enc.Code, cells_per_image: float) -> float:
    """``p`` that puts ``cells_per_image`` cells on the array (s = +-1 at +-half of them)."""
    return math.tan(0.5 * cells_per_image * code.cell_rad)


def nominal_aperture(n_diodes: int) -> np.ndarray:
    """Design aperture ``(t-, t+)``: a diode of pitch ``2/n`` blurred by about one pitch."""
    pitch = 2.0 / n_diodes
    return np.array([0.6 * pitch, 1.6 * pitch])


@dataclass
class EncoderScenario:
    """A self-calibration run: ``n_positions`` frames of each array, disk positions spread over a revolution.

    Parameters are the truth; defaults are the patent's scale (m = 1023, n = 1024, N = 240) with about
    12 cells per image.
    """

    l: int = 10
    n_diodes: int = 1024
    n_positions: int = 240
    cells_per_image: float = 12.0
    n_arrays: int = 1
    array_offsets_rad: tuple[float, ...] = ()   # arrays 1.. (default: spread evenly)
    harmonic_rad: float = 2e-6                   # amplitude of each graduation-error harmonic
    harmonics: tuple[int, ...] = (1, 2, 3, 5)
    random_rad: float = 1e-6                     # independent per-edge graduation error (1 sigma)
    p_error: float = 2e-3                        # relative error of the true p against the nominal one
    q: float = 5e-3
    eccentricity: tuple[float, float] = (0.0, 0.0)   # code centre offset (x, y) in the disk frame, code radii
    aperture_scale: tuple[float, float] = (1.05, 0.97)   # true aperture / nominal
    a0: float = 30.0                             # dark level, counts
    intensity: float = 1000.0                    # illumination at the centre, counts
    profile: tuple[float, float] = (0.05, -0.25)  # P1, P2 coefficients of the illumination, relative
    intensity_drift: float = 0.02                # per-frame relative light intensity change (1 sigma)
    noise_sigma: float = 2.0                     # counts per diode
    adc_max: float = 4095.0
    prnu_sigma: float = 0.0                      # per-diode gain (1 sigma, relative)
    response_compression: float = 0.0            # diode response s - c s^2 / adc_max: c = relative loss at full
    # scale (a compressive, saturating photodiode / ADC chain; not in the audit's catalog)
    temperature_scale_per_degC: float = 0.0      # dp/p per degC (temperature-dependent scale)
    temperature_range_degC: float = 0.0          # temperature swing over the recording
    temperature_profile: str = "centred"         # "centred" about T_ref, or "ramp" from T_ref upwards
    a0_per_degC: float = 0.0                     # dark level drift, counts per degC
    aperture_per_degC: float = 0.0               # relative aperture (blur) change per degC
    intensity_per_degC: float = 0.0              # relative light level change per degC
    frame_period_s: float = 1.0
    seed: int = 0
    positions_rad: np.ndarray | None = None      # explicit positions (else spread over a revolution)
    jitter: float = 0.5                          # random position jitter, in position steps
    _rng_state: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        self.code = enc.Code.m_sequence(self.l)
        code = self.code
        nominal = code.nominal_edge_angles()
        g = np.zeros(code.n_edges)
        for k in self.harmonics:
            g += self.harmonic_rad * np.sin(k * nominal + rng.uniform(0, 2 * math.pi))
        g += self.random_rad * rng.normal(size=code.n_edges)
        self.graduation_rad = g - g[0]
        self.edges_rad = nominal + self.graduation_rad
        N = self.n_positions
        if self.positions_rad is None:
            steps = (np.arange(N) + self.jitter * rng.uniform(-0.5, 0.5, N)) * 2 * math.pi / N
            self.beta_rad = np.remainder(steps + rng.uniform(0, 2 * math.pi), 2 * math.pi)
        else:
            self.beta_rad = np.asarray(self.positions_rad, dtype=float)
            N = self.n_positions = self.beta_rad.size
        self.p_nominal = nominal_p(code, self.cells_per_image)
        offsets = list(self.array_offsets_rad) or [2 * math.pi * k / self.n_arrays + 0.1 * k
                                                   for k in range(1, self.n_arrays)]
        self.offsets_rad = np.array([0.0] + offsets[:self.n_arrays - 1])
        eps_x, eps_y = self.eccentricity
        self.geometry = []
        self.aperture = []
        for k in range(self.n_arrays):
            p = self.p_nominal * (1 + self.p_error * (1 + 0.5 * k))
            self.geometry.append(np.array([p, self.q * (1 - 0.3 * k), -eps_y, eps_x, 0.0, 0.0]))
            self.aperture.append(nominal_aperture(self.n_diodes) * np.asarray(self.aperture_scale))
        t = np.arange(N) * self.frame_period_s
        self.t_ns = T0_NS + np.round(t * 1e9).astype(np.int64)
        phase = np.linspace(0, 1, N)
        if self.temperature_profile not in ("centred", "ramp"):
            raise ValueError(f"temperature_profile must be 'centred' or 'ramp', not {self.temperature_profile!r}")
        start = -0.5 if self.temperature_profile == "centred" else 0.0
        self.temperature_degC = (TEMPERATURE_REF_DEGC + self.temperature_range_degC * (phase + start)
                                 + 0.2 * np.sin(2 * math.pi * 3 * phase))
        base = np.array([1.0, self.profile[0], self.profile[1]]) * self.intensity
        light = 1 + self.intensity_per_degC * (self.temperature_degC - TEMPERATURE_REF_DEGC)
        self.illumination = [base[None, :] * (1 + self.intensity_drift * rng.normal(size=(N, 1))) * light[:, None]
                             for _ in range(self.n_arrays)]
        self.gain = [self.prnu_sigma * rng.normal(size=self.n_diodes) for _ in range(self.n_arrays)]
        for k in range(self.n_arrays):
            if self.prnu_sigma > 0:
                # a gain pattern shaped like the illumination basis is the illumination: keep PRNU orthogonal
                P = enc.illumination_basis(enc.diode_centres(self.n_diodes), 2)
                g_k = self.gain[k]
                self.gain[k] = g_k - P @ np.linalg.lstsq(P, g_k, rcond=None)[0]

    # -- model ------------------------------------------------------------------------------------------------
    def geometry_at(self, k: int, J: int) -> np.ndarray:
        """Array k's geometry for frame J (temperature-dependent p)."""
        g = self.geometry[k].copy()
        g[0] *= 1 + self.temperature_scale_per_degC * (self.temperature_degC[J] - TEMPERATURE_REF_DEGC)
        return g

    def aperture_at(self, k: int, J: int) -> np.ndarray:
        """Array k's aperture ``(t-, t+)`` for frame J (temperature-dependent blur)."""
        return self.aperture[k] * (1 + self.aperture_per_degC * (self.temperature_degC[J] - TEMPERATURE_REF_DEGC))

    def a0_at(self, J: int) -> float:
        """Dark level for frame J (temperature-dependent), counts."""
        return self.a0 + self.a0_per_degC * (self.temperature_degC[J] - TEMPERATURE_REF_DEGC)

    def exact_frames(self, k: int = 0) -> np.ndarray:
        """Noise-free frames (N, n) of array k."""
        s = enc.diode_centres(self.n_diodes)
        frames = np.empty((self.n_positions, self.n_diodes))
        for J, beta in enumerate(self.beta_rad):
            geometry = self.geometry_at(k, J)
            b = beta + self.offsets_rad[k]
            edges, alpha = enc.visible_bars(self.code, b, geometry, self.edges_rad, margin_s=0.3)
            w = enc.edge_weights(self.code, edges, geometry)
            frames[J], _ = enc.frame_signal(s, alpha, w, b, geometry, self.aperture_at(k, J),
                                            self.illumination[k][J], self.a0_at(J),
                                            self.gain[k] if self.prnu_sigma > 0 else None,
                                            jacobians=False)
        return frames - self.response_compression * frames**2 / self.adc_max

    def noise(self, seed, k: int = 0) -> np.ndarray:
        rng = np.random.default_rng([seed, k, 7001])
        return self.noise_sigma * rng.normal(size=(self.n_positions, self.n_diodes))

    def perturbed_frames(self, seed, k: int = 0) -> np.ndarray:
        return np.clip(self.exact_frames(k) + self.noise(seed, k), 0.0, self.adc_max)

    # -- recording --------------------------------------------------------------------------------------------
    def sensor_yaml(self, k: int) -> dict:
        """What a user knows of array k: the design values, not the truth."""
        return {"sensor_type": "photodiode_array", "n_diodes": self.n_diodes, "code_length_l": self.l,
                "geometry_nominal": {"p": self.p_nominal, "q": 0.0},
                "aperture_nominal": nominal_aperture(self.n_diodes).tolist(),
                "array_offset_nominal_rad": float(self.offsets_rad[k]) if k else 0.0,
                "adc_max": self.adc_max, "noise_sigma_counts": self.noise_sigma,
                "illumination_degree": 2, "rate_hz": 1.0 / self.frame_period_s}

    def measurements(self, seed: int | None) -> tuple[Recording, dict[str, bytes]]:
        sensors, files = {}, {}
        for k in range(self.n_arrays):
            name = f"array{k}"
            frames = self.exact_frames(k) if seed is None else self.perturbed_frames(seed, k)
            sensors[name] = SensorData(name, self.t_ns.copy(), {"temperature": self.temperature_degC.copy()},
                                       {"temperature": "degC"}, self.sensor_yaml(k))
            files[f"{name}/frames.npy"] = npy_bytes(frames)
        return Recording(None, sensors), files

    def exact_measurements(self) -> tuple[Recording, dict[str, bytes]]:
        return self.measurements(None)

    def perturbed_measurements(self, seed: int) -> tuple[Recording, dict[str, bytes]]:
        return self.measurements(seed)

    def reference(self, indices, sigma_rad: float, seed: int, offset_rad: float = 0.0123) -> SensorData:
        """Reference angles ``beta_J + offset + noise`` for some positions (mixed calibration).

        The reference instrument has its own zero (``offset_rad``), which the calibration estimates.
        """
        idx = np.sort(np.asarray(indices, dtype=int))
        rng = np.random.default_rng([seed, 9001])
        angle = self.beta_rad[idx] + offset_rad + sigma_rad * rng.normal(size=idx.size)
        return SensorData("reference", self.t_ns[idx].copy(), {"angle": angle}, {"angle": "rad"},
                          {"sensor_type": "reference_angle", "angle_sigma_rad": sigma_rad})

    def truth(self) -> dict:
        return to_plain({
            "edges_rad": self.edges_rad, "graduation_rad": self.graduation_rad, "beta_rad": self.beta_rad,
            "arrays": [{"geometry": self.geometry[k], "aperture": self.aperture[k], "a0": self.a0,
                        "offset_rad": float(self.offsets_rad[k]), "illumination": self.illumination[k],
                        "gain": self.gain[k]} for k in range(self.n_arrays)],
            "eccentricity": list(self.eccentricity), "noise_sigma": self.noise_sigma,
            "temperature_scale_per_degC": self.temperature_scale_per_degC,
            "temperature_ref_degC": TEMPERATURE_REF_DEGC, "prnu_sigma": self.prnu_sigma,
            "drift": {"a0_per_degC": self.a0_per_degC, "aperture_per_degC": self.aperture_per_degC,
                      "intensity_per_degC": self.intensity_per_degC,
                      "p": [float(self.geometry_at(0, J)[0]) for J in range(self.n_positions)],
                      "aperture": [self.aperture_at(0, J) for J in range(self.n_positions)],
                      "a0": [self.a0_at(J) for J in range(self.n_positions)]}}, "truth")

    def write(self, path, seed: int | None = 0, overwrite: bool = False, reference: dict | None = None) -> Path:
        """Write the recording (``seed=None``: exact frames); ``reference={"every": 10, "sigma_rad": 1e-6}``
        adds ``reference/data.csv`` for every 10th position."""
        rec, files = self.measurements(seed)
        if reference:
            idx = np.arange(0, self.n_positions, int(reference.get("every", 10)))
            rec.sensors["reference"] = self.reference(idx, float(reference.get("sigma_rad", 1e-6)),
                                                      seed or 0, float(reference.get("offset_rad", 0.0123)))
        return write_recording(rec, path, truth=self.truth(), overwrite=overwrite, extra_files=files)


def npy_bytes(array: np.ndarray) -> bytes:
    import io
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()
