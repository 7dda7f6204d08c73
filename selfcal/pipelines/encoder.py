"""Use cases ``selfcal simulate|calibrate|measure encoder``: recording in, result object out.

The calibration YAML (``to_dict``) holds every estimated number with its 1-sigma; the joint covariance of the
edges and array parameters (needed to carry the calibration's uncertainty into each measured angle) goes to a
companion ``.npy`` file named in the YAML (``covariance_file``).
"""
from __future__ import annotations

import copy
import io
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from selfcal.baselines.encoder import patent_calibration
from selfcal.core.progress import quiet
from selfcal.graphs.encoder import calibration as ge
from selfcal.graphs.encoder import durable as ged
from selfcal.io.encoder import EncoderRecordingError, read_encoder_arrays, read_reference
from selfcal.io.recording import Recording, read_recording
from selfcal.pipelines.fleet import flat_columns, register_task
from selfcal.models import encoder as enc
from selfcal.sim.encoder import EncoderScenario

log = logging.getLogger(__name__)


@dataclass
class SimulationResult:
    path: Path
    scenario: EncoderScenario

    def summary(self) -> str:
        s = self.scenario
        return (f"{self.path}: {s.n_arrays} array(s) x {s.n_positions} frames of {s.n_diodes} diodes, code "
                f"m = {s.code.m}, ~{s.cells_per_image:g} cells per image; graduation errors RMS "
                f"{np.sqrt(np.mean(s.graduation_rad**2)) * 1e6:.2f} urad")


def simulate_encoder(out, seed: int = 0, overwrite: bool = False, reference_every: int = 0,
                     reference_sigma_rad: float = 1e-6, **options) -> SimulationResult:
    """Write a simulated recording (truth in ``truth/``); ``options`` are :class:`EncoderScenario` fields."""
    scenario = EncoderScenario(seed=seed, **options)
    reference = {"every": reference_every, "sigma_rad": reference_sigma_rad} if reference_every else None
    path = scenario.write(out, seed=seed, overwrite=overwrite, reference=reference)
    return SimulationResult(Path(path), scenario)


def problem_from_recording(rec: Recording, frames: dict | None = None, use_reference: bool = True) -> ge.Problem:
    arrays = read_encoder_arrays(rec, frames)
    code = enc.Code.m_sequence(int(arrays[0].meta["code_length_l"]))
    data = []
    for a in arrays:
        temperature = a.channels.get("temperature")
        data.append(ge.ArrayData(
            a.name, a.frames, a.geometry_nominal(), a.aperture_nominal(),
            float(a.meta.get("array_offset_nominal_rad", 0.0)),
            float(a.meta["adc_max"]) if "adc_max" in a.meta else None,
            float(a.meta.get("noise_sigma_counts", 1.0)), int(a.meta.get("illumination_degree", 2)),
            float(a.meta.get("eccentricity_kappa", 1.0)), temperature))
    reference = None
    ref = read_reference(rec) if use_reference else None
    if ref is not None:
        index = {int(t): J for J, t in enumerate(arrays[0].t_ns)}
        rows = [(index[int(t)], a) for t, a in zip(ref.t_ns, ref.angle_rad) if int(t) in index]
        if not rows:
            raise EncoderRecordingError(f"{rec.path}/reference/data.csv: no timestamp matches a frame of array0")
        reference = ge.Reference(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), ref.sigma_rad)
    return ge.decode_problem(code, data, reference)


@dataclass
class EncoderCalibrationResult:
    estimate: ge.Estimate
    problem: ge.Problem
    t_ns: np.ndarray
    seconds: float
    flags: dict = field(default_factory=dict)   # "array/J" -> flag

    def to_dict(self, covariance_file: str | None = None) -> dict:
        est, code = self.estimate, self.problem.code
        arrays = {}
        for k, (a, data) in enumerate(zip(est.arrays, self.problem.arrays)):
            entry = {
                "n_diodes": data.n,
                "geometry": dict(zip(enc.GEOMETRY_NAMES, a.geometry.tolist())),
                "geometry_sigma": {name: (None if math.isnan(s) else float(s))
                                   for name, s in zip(enc.GEOMETRY_NAMES, a.geometry_sigma)},
                "aperture": a.aperture.tolist(), "aperture_sigma": a.aperture_sigma.tolist(),
                "a0_counts": a.a0, "a0_sigma_counts": a.a0_sigma,
                "offset_rad": a.offset_rad, "offset_sigma_rad": a.offset_sigma_rad,
                "noise_sigma_counts": a.noise_sigma, "residual_rms_counts": a.residual_rms,
                "illumination_degree": data.illumination_degree, "adc_max": data.adc_max}
            if a.temperature_scale is not None:
                entry["temperature_scale_per_degC"] = a.temperature_scale
                entry["temperature_scale_sigma_per_degC"] = a.temperature_scale_sigma
            arrays[data.name] = entry
        nominal = code.nominal_edge_angles()
        used = np.isfinite(est.beta_rad)
        out = {
            "system": "encoder",
            "code": {"l": code.l, "m": code.m, "n_edges": code.n_edges},
            "gauge": "edge 0 held at its nominal angle 2 pi k_0 / m (only alpha - beta is observable)",
            "model": {"geometry_free": [enc.GEOMETRY_NAMES[i] for i in est.model.geometry_free],
                      "eccentricity": est.model.eccentricity, "temperature_scale": est.model.temperature_scale},
            "arrays": arrays,
            "edges_rad": est.edges_rad.tolist(),
            "edges_sigma_rad": [None if math.isnan(s) else float(s) for s in est.edges_sigma_rad],
            "graduation_error_rad": (est.edges_rad - nominal).tolist(),
            "positions": {"timestamp_ns": [int(t) for t in self.t_ns[used]],
                          "beta_rad": est.beta_rad[used].tolist(), "beta_sigma_rad": est.beta_sigma_rad[used].tolist()},
            "frames": {"total": int(self.problem.n_positions), "used": int(used.sum()), "flagged": self.flags},
            "units": {"angles": "rad", "geometry": "dimensionless (p, q, u, v, x, y of formula (0))",
                      "aperture": "array half-lengths (t-, t+)", "a0": "counts"},
            "iterations": est.iterations, "seconds": self.seconds, "notes": est.notes,
        }
        if est.eccentricity is not None:
            out["eccentricity"] = est.eccentricity.tolist()
            out["eccentricity_sigma"] = est.eccentricity_sigma.tolist()
        if est.reference_offset_rad is not None:
            out["reference_offset_rad"] = est.reference_offset_rad
            out["reference_offset_sigma_rad"] = est.reference_offset_sigma_rad
        if covariance_file:
            out["covariance_file"] = covariance_file
            out["covariance_layout"] = [[name, int(i)] for name, i in est.covariance_layout]
        return out

    def covariance_bytes(self) -> bytes:
        buf = io.BytesIO()
        np.save(buf, self.estimate.calibration_covariance, allow_pickle=False)
        return buf.getvalue()

    def summary(self) -> str:
        est = self.estimate
        a = est.arrays[0]
        used = np.isfinite(est.beta_rad)
        grad = est.edges_rad - self.problem.code.nominal_edge_angles()
        return (f"{int(used.sum())}/{self.problem.n_positions} frames, {np.isfinite(est.edges_sigma_rad).sum()} "
                f"edges in {self.seconds:.1f} s ({est.iterations} LM iterations); graduation error RMS "
                f"{np.sqrt(np.mean(grad**2)) * 1e6:.3f} urad, median edge sigma "
                f"{np.nanmedian(est.edges_sigma_rad[1:]) * 1e6:.3f} urad; p = {a.geometry[0]:.8g} +- "
                f"{a.geometry_sigma[0]:.2g} (dimensionless); noise {a.noise_sigma:.3g} counts"
                + (f"; {len(self.flags)} frames flagged" if self.flags else ""))


def calibrate_encoder(rec: Recording, model: ge.EncoderModel = ge.EncoderModel(), frames: dict | None = None,
                      use_reference: bool = True, covariance: bool = True,
                      progress=quiet) -> EncoderCalibrationResult:
    """Batch ML self-calibration of an encoder recording (mixed when it holds ``reference/``);
    ``progress(stage)`` is told each stage as it starts (:mod:`selfcal.core.progress`)."""
    start = time.perf_counter()
    progress("read and decode the frames")
    problem = problem_from_recording(rec, frames, use_reference)
    flags = {f"{a.name}/{J}": d.flag for a, dec in zip(problem.arrays, problem.decoded)
             for J, d in enumerate(dec) if not d.ok}
    for key, flag in flags.items():
        log.warning("frame %s not used: %s", key, flag)
    # the patent's start values (decoding + interpolated crossings, iterated averages) on array 0
    progress("start values (the patent's method)")
    a0 = problem.arrays[0]
    base = patent_calibration(a0.frames, problem.code, a0.geometry_nominal, a0.adc_max, a0.noise_sigma)
    beta = np.where(np.isfinite(base.beta_rad), base.beta_rad, problem.beta0)
    geometry = [base.geometry] + [a.geometry_nominal for a in problem.arrays[1:]]
    progress("ML calibration (factor graph" + (", covariance)" if covariance else ")"))
    est = ge.calibrate(problem, model, covariance=covariance,
                       start={"edges": base.edges_rad, "beta": beta, "geometry": geometry})
    arrays = read_encoder_arrays(rec, frames)
    return EncoderCalibrationResult(est, problem, arrays[0].t_ns, time.perf_counter() - start, flags)


@dataclass
class MeasureResult:
    t_ns: np.ndarray
    beta_rad: np.ndarray
    sigma_rad: np.ndarray
    sigma_noise_rad: np.ndarray
    flags: list[str]
    array: str
    drift_columns: list[tuple[str, np.ndarray]] = field(default_factory=list)   # ("p [1]", values), ...
    updated_calibration: dict | None = None     # --track-drift: the calibration after the run
    updated_covariance: np.ndarray | None = None
    seconds: float = 0.0

    def summary(self) -> str:
        ok = np.array([not f for f in self.flags])
        text = (f"{self.array}: {int(ok.sum())}/{ok.size} frames measured, median sigma "
                f"{np.nanmedian(self.sigma_rad[ok]) * 1e6 if ok.any() else float('nan'):.3f} urad"
                + (f"; flagged: {dict(zip(*np.unique([f for f in self.flags if f], return_counts=True)))}"
                   if not ok.all() else ""))
        if self.drift_columns:
            cols = dict(self.drift_columns)
            p, ps = cols["p [1]"], cols["p_sigma [1]"]
            text += (f"; drift tracked ({ok.size / max(self.seconds, 1e-9):.1f} frames/s): p {p[0]:.8g} -> "
                     f"{p[-1]:.8g} +- {ps[-1]:.2g} (dimensionless), "
                     f"a0 {cols['a0 [counts]'][0]:.4g} -> {cols['a0 [counts]'][-1]:.4g} "
                     f"+- {cols['a0_sigma [counts]'][-1]:.2g} counts")
        return text


def load_calibration(calibration: dict, covariance: np.ndarray | None, array: str = "array0"):
    """(code, edges, ArrayCalibration, edge covariance index) from a calibration YAML dict."""
    try:
        code = enc.Code.m_sequence(int(calibration["code"]["l"]))
        a = calibration["arrays"][array]
        edges = np.asarray(calibration["edges_rad"], dtype=float)
        free = tuple(enc.GEOMETRY_NAMES.index(n) for n in calibration["model"]["geometry_free"])
        geometry = np.array([a["geometry"][n] for n in enc.GEOMETRY_NAMES], dtype=float)
    except (KeyError, TypeError, ValueError) as err:
        raise EncoderRecordingError(f"calibration file: missing or bad entry ({err})") from None
    if edges.size != code.n_edges:
        raise EncoderRecordingError(f"calibration file: {edges.size} edges, code l={code.l} has {code.n_edges}")
    cov_index, edge_index = {}, {}
    layout = calibration.get("covariance_layout") or []
    offset = 0
    for name, idx in layout:
        dim = {"edge": 1, "geometry": len(free), "aperture": 2, "a0": 1, "offset": 1}[name]
        if name == "edge":
            edge_index[int(idx)] = offset
        elif f"array{idx}" == array:
            cov_index[name] = list(range(offset, offset + dim))
        offset += dim
    if covariance is not None and covariance.shape != (offset, offset):
        raise EncoderRecordingError(f"covariance file: shape {covariance.shape}, the calibration's layout needs "
                                    f"({offset}, {offset})")
    cal = ge.ArrayCalibration(geometry, free, np.asarray(a["aperture"], dtype=float), float(a["a0_counts"]),
                              float(a["offset_rad"]), float(a["noise_sigma_counts"]),
                              int(a.get("illumination_degree", 2)), a.get("adc_max"), cov_index)
    return code, edges, cal, (edge_index if covariance is not None else None)


def durable_prior(calibration: dict, covariance: np.ndarray | None, array: str = "array0") -> ged.DurablePrior:
    """The calibration of ``array`` as the durable estimator's prior (edges, geometry, aperture, a0, joint)."""
    code, edges, cal, edge_index = load_calibration(calibration, covariance, array)
    if covariance is None or not edge_index or any(k not in cal.cov_index for k in ("geometry", "aperture", "a0")):
        raise EncoderRecordingError("--track-drift needs the calibration's covariance file (covariance_file with "
                                    "edges, geometry, aperture and a0 of the array): re-run `selfcal calibrate "
                                    "encoder --out CAL.yaml`")
    edge_vars = sorted(edge_index)
    idx = [edge_index[e] for e in edge_vars] + cal.cov_index["geometry"] + cal.cov_index["aperture"] \
        + cal.cov_index["a0"]
    return ged.DurablePrior(code, edges, edge_vars, cal.geometry, cal.geometry_free, cal.aperture, cal.a0,
                            cal.noise_sigma, covariance[np.ix_(idx, idx)], cal.illumination_degree, cal.adc_max,
                            cal.offset_rad)


def measure_encoder(rec: Recording, calibration: dict, covariance: np.ndarray | None = None,
                    array: str = "array0", frames: dict | None = None, track_drift: bool = False,
                    drift: ged.DriftModel = ged.DriftModel(), progress=quiet) -> MeasureResult:
    """ML angle of every frame of ``array`` with the calibration; flagged frames get NaN and their flag.

    ``track_drift``: durable self-calibration (:mod:`selfcal.graphs.encoder.durable`): the calibration is the
    prior, iSAM2 follows the drifting geometry, aperture and dark level frame by frame (columns
    ``drift_columns``) and refines the edges; the result carries the updated calibration.
    ``progress(stage, done, total)`` counts the frames (:mod:`selfcal.core.progress`).
    """
    arrays = {a.name: a for a in read_encoder_arrays(rec, frames)}
    if array not in arrays:
        raise EncoderRecordingError(f"{rec.path}: no sensor {array!r} (arrays: {', '.join(arrays)})")
    data = arrays[array]
    code, edges, cal, edge_index = load_calibration(calibration, covariance, array)
    if int(data.meta["code_length_l"]) != code.l:
        raise EncoderRecordingError(f"{rec.path}/{array}: code l={data.meta['code_length_l']}, the calibration "
                                    f"is for l={code.l}")
    if data.n_diodes != int(calibration["arrays"][array]["n_diodes"]):
        raise EncoderRecordingError(f"{rec.path}/{array}: {data.n_diodes} diodes, the calibration is for "
                                    f"{calibration['arrays'][array]['n_diodes']}")
    if track_drift:
        return _measure_durable(data, calibration, covariance, array, drift, progress)
    out = []
    for i, frame in enumerate(data.frames):
        progress("frames", i, len(data.frames))
        out.append(ge.measure_frame(frame, code, edges, cal, covariance, edge_index))
    return MeasureResult(data.t_ns, np.array([m.beta_rad if not m.flag else np.nan for m in out]),
                         np.array([m.sigma_rad if not m.flag else np.nan for m in out]),
                         np.array([m.sigma_noise_rad for m in out]), [m.flag for m in out], array)


def _measure_durable(data, calibration: dict, covariance, array: str, drift: ged.DriftModel,
                     progress) -> MeasureResult:
    prior = durable_prior(calibration, covariance, array)
    start = time.perf_counter()
    estimator = ged.DurableEncoder(prior, drift)
    steps = []
    for i, (t_ns, frame) in enumerate(zip(data.t_ns, data.frames)):
        progress("frames (iSAM2, drift tracked)", i, len(data.frames))
        steps.append(estimator.add_frame(int(t_ns), frame))
    progress("updated calibration")
    seconds = time.perf_counter() - start
    columns = []
    for i, g in enumerate(prior.geometry_free):
        name = enc.GEOMETRY_NAMES[g]
        columns += [(f"{name} [1]", np.array([s.geometry[i] for s in steps])),
                    (f"{name}_sigma [1]", np.array([s.geometry_sigma[i] for s in steps]))]
    for i, name in enumerate(enc.APERTURE_NAMES):
        columns += [(f"{name} [1]", np.array([s.aperture[i] for s in steps])),
                    (f"{name}_sigma [1]", np.array([s.aperture_sigma[i] for s in steps]))]
    columns += [("a0 [counts]", np.array([s.a0 for s in steps])),
                ("a0_sigma [counts]", np.array([s.a0_sigma for s in steps]))]
    updated, updated_cov = _updated_calibration(calibration, covariance, array, prior, estimator, data)
    return MeasureResult(data.t_ns, np.array([s.beta_rad for s in steps]), np.array([s.beta_sigma_rad for s in steps]),
                         np.full(len(steps), np.nan), [s.flag for s in steps], array, columns, updated, updated_cov,
                         seconds)


def _updated_calibration(calibration: dict, covariance: np.ndarray, array: str, prior: ged.DurablePrior,
                         estimator: ged.DurableEncoder, data) -> tuple[dict, np.ndarray]:
    """The calibration after a durable run: edges and the array's parameters replaced by the posterior, the
    covariance's rows of those replaced by the posterior's joint covariance (cross terms with other arrays'
    parameters, which the run did not see, set to zero)."""
    mean, post = estimator.posterior()
    out = copy.deepcopy(calibration)
    E = len(prior.edge_vars)
    nf = len(prior.geometry_free)
    sd = np.sqrt(np.diag(post))
    edges = np.asarray(out["edges_rad"], dtype=float)
    edges[prior.edge_vars] = mean[:E]
    sigma = [None if s is None else float(s) for s in out["edges_sigma_rad"]]
    for e, s_e in zip(prior.edge_vars, sd[:E]):
        sigma[e] = float(s_e)
    out["edges_rad"], out["edges_sigma_rad"] = edges.tolist(), sigma
    out["graduation_error_rad"] = (edges - prior.code.nominal_edge_angles()).tolist()
    a = out["arrays"][array]
    for i, g in enumerate(prior.geometry_free):
        a["geometry"][enc.GEOMETRY_NAMES[g]] = float(mean[E + i])
        a["geometry_sigma"][enc.GEOMETRY_NAMES[g]] = float(sd[E + i])
    a["aperture"], a["aperture_sigma"] = mean[E + nf:E + nf + 2].tolist(), sd[E + nf:E + nf + 2].tolist()
    a["a0_counts"], a["a0_sigma_counts"] = float(mean[-1]), float(sd[-1])
    out["durable"] = {"array": array, "frames_used": int(estimator.n_frames), "frames_total": int(len(data.t_ns)),
                      "last_timestamp_ns": int(data.t_ns[-1]) if len(data.t_ns) else None,
                      "process_noise_per_sqrt_s": {"p_rel": estimator.drift.p_rel, "q": estimator.drift.q,
                                                   "aperture_rel": estimator.drift.aperture_rel,
                                                   "a0_counts": estimator.drift.a0_counts}}
    out.setdefault("notes", []).append(
        f"updated by durable self-calibration (iSAM2) over {estimator.n_frames} frames of {array}; positions are "
        "those of the original calibration")
    _, _, cal, edge_index = load_calibration(calibration, covariance, array)
    idx = [edge_index[e] for e in prior.edge_vars] + cal.cov_index["geometry"] + cal.cov_index["aperture"] \
        + cal.cov_index["a0"]
    cov = covariance.copy()
    cov[idx, :] = 0.0
    cov[:, idx] = 0.0
    cov[np.ix_(idx, idx)] = post
    return out, cov


def audit_system(rec: Recording, base: str = "ml", sensors: list[str] | None = None, frames: dict | None = None):
    """The audit's view of an encoder recording: decoded frames, the patent's start values, the ML base fit
    (the only base; ``sensors`` is not used: every array of the recording is audited)."""
    from selfcal.audit.encoder import EncoderAudit
    problem = problem_from_recording(rec, frames, use_reference=False)
    a0 = problem.arrays[0]
    base = patent_calibration(a0.frames, problem.code, a0.geometry_nominal, a0.adc_max, a0.noise_sigma)
    beta = np.where(np.isfinite(base.beta_rad), base.beta_rad, problem.beta0)
    geometry = [base.geometry] + [a.geometry_nominal for a in problem.arrays[1:]]
    return EncoderAudit(problem, {"edges": base.edges_rad, "beta": beta, "geometry": geometry})


# --- fleet ------------------------------------------------------------------------------------------------------

def calibrate_encoder_task(recording_path, options: dict) -> dict:
    """``selfcal calibrate encoder`` as columns: per array the geometry, aperture and dark level with their
    sigmas and the residual; the graduation error's RMS and largest value, the median edge sigma, frames."""
    cal = calibrate_encoder(read_recording(recording_path), use_reference=options.get("reference", True))
    d = cal.to_dict()
    graduation = np.asarray(d["graduation_error_rad"])
    sigma = np.array([np.nan if s is None else s for s in d["edges_sigma_rad"]], dtype=float)
    return {"edges": d["code"]["n_edges"], "graduation_rms_rad": float(np.sqrt(np.mean(graduation**2))),
            "graduation_max_rad": float(np.max(np.abs(graduation))),
            "edge_sigma_median_rad": float(np.nanmedian(sigma)),
            "frames_used": d["frames"]["used"], "frames_flagged": len(d["frames"]["flagged"]),
            "seconds": d["seconds"], **flat_columns({"arrays": d["arrays"]})}


register_task("calibrate-encoder", calibrate_encoder_task, ("reference",),
              "encoder self-calibration from the diode array's own images")
