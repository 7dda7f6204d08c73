"""Encoder self-calibration (patent seed 000) as a factor graph: batch ML, mixed, multi-array, durable (iSAM2).

Variables (keys below): the disk position ``beta_J`` of every position, the code edges ``alpha_e``, and per
array its free geometry (``p, q`` by default), aperture ``(t-, t+)``, dark level ``a0``, its offset (arrays
1..k), and the illumination profile of each of its frames.  One :func:`selfcal.factors.encoder.frame_factor`
per frame.  Maximum likelihood under white Gaussian diode noise (the patent's (14)) is the least-squares
solution; GTSAM's Levenberg-Marquardt solves it by sparse elimination (COLAMD ordering: frames, then edges,
then the few shared parameters).

Gauge: only ``alpha - beta`` is observable (claim 6).  It is fixed explicitly: edge 0 is a constant at its
nominal angle (not a variable), so every angle is reported relative to the code's first edge.

Loose priors: every edge also gets a prior at its nominal angle with ``EDGE_PRIOR_RAD`` (1 mrad, a thousand
times any graduation error): it changes well-seen edges by less than 1e-6 of their sigma and keeps an edge that
is only ever seen at the array's very end from making the system singular.

Mixed calibration: reference angles ``beta_ref,J = beta_J + c`` (the reference's own zero ``c`` estimated)
enter as factors on ``beta_J`` and ``c``.  Multi-array: frames of array k see ``beta_J + o_k``; ``o_k`` is
estimated.  Observability of the eccentricity is checked numerically (:func:`eccentricity_observability`).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from selfcal.factors import encoder as fenc
from selfcal.core.solve import DegenerateDataError
from selfcal.models import encoder as enc

log = logging.getLogger(__name__)

EDGE_PRIOR_RAD = 1e-3
ILLUMINATION_STRIDE = 1_000_000


def B(J: int) -> int:
    return gtsam.symbol("b", J)


def EDGE(e: int) -> int:
    return gtsam.symbol("e", e)


def GEOMETRY(k: int) -> int:
    return gtsam.symbol("g", k)


def APERTURE(k: int) -> int:
    return gtsam.symbol("t", k)


def A0(k: int) -> int:
    return gtsam.symbol("z", k)


def OFFSET(k: int) -> int:
    return gtsam.symbol("o", k)


def TEMPERATURE(k: int) -> int:
    return gtsam.symbol("k", k)


def GAIN(k: int) -> int:
    return gtsam.symbol("r", k)


def ILLUMINATION(k: int, J: int) -> int:
    return gtsam.symbol("c", k * ILLUMINATION_STRIDE + J)


ECCENTRICITY = gtsam.symbol("x", 0)
REFERENCE_OFFSET = gtsam.symbol("f", 0)


# --- data ------------------------------------------------------------------------------------------------------

@dataclass
class ArrayData:
    """One diode array's frames and what its sensor.yaml says (design values, not truth)."""

    name: str
    frames: np.ndarray                      # (N, n) counts
    geometry_nominal: np.ndarray            # (6,)
    aperture_nominal: np.ndarray            # (2,)
    offset_nominal_rad: float = 0.0
    adc_max: float | None = None
    noise_sigma: float = 1.0                # counts, start value (re-estimated from the residuals)
    illumination_degree: int = 2
    kappa: float = 1.0                      # eccentricity geometry factor (standard layout: 1)
    temperature_degC: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.frames.shape[1])


@dataclass(frozen=True)
class EncoderModel:
    """What the graph estimates besides positions, edges, illumination, aperture and a0."""

    geometry_free: tuple[int, ...] = (0, 1)     # indices into (p, q, u, v, x, y)
    eccentricity: bool = False
    temperature_scale: bool = False
    prnu: bool = False
    edges_fixed: bool = False                   # edges are constants (from a previous calibration)


@dataclass
class Reference:
    """External reference angles for some positions (mixed calibration): ``angle = beta_J + c + noise``."""

    positions: np.ndarray   # indices J
    angle_rad: np.ndarray
    sigma_rad: float


@dataclass
class Problem:
    code: enc.Code
    arrays: list[ArrayData]
    decoded: list[list[enc.DecodedFrame]]      # [array][J]
    beta0: np.ndarray                           # (N,) start positions (NaN: no array decoded it)
    reference: Reference | None = None

    @property
    def n_positions(self) -> int:
        return int(self.arrays[0].frames.shape[0])

    def used_positions(self) -> np.ndarray:
        return np.flatnonzero(np.isfinite(self.beta0))

    def flags(self) -> list[list[str]]:
        return [[d.flag for d in dec] for dec in self.decoded]


def decode_problem(code: enc.Code, arrays: list[ArrayData], reference: Reference | None = None) -> Problem:
    """Decode every frame of every array; start positions from array 0, else from another array's offset."""
    N = arrays[0].frames.shape[0]
    decoded = []
    for arr in arrays:
        if arr.frames.shape[0] != N:
            raise DegenerateDataError(f"{arr.name} has {arr.frames.shape[0]} frames, {arrays[0].name} has {N}: "
                                      "arrays must record the same positions")
        decoded.append([enc.decode_frame(f, code, arr.geometry_nominal, adc_max=arr.adc_max,
                                         noise_sigma=arr.noise_sigma) for f in arr.frames])
    beta0 = np.full(N, np.nan)
    for J in range(N):
        for k, arr in enumerate(arrays):
            if decoded[k][J].ok:
                beta0[J] = decoded[k][J].beta_rad - arr.offset_nominal_rad
                break
    return Problem(code, arrays, decoded, beta0, reference)


# --- estimate --------------------------------------------------------------------------------------------------

@dataclass
class ArrayEstimate:
    geometry: np.ndarray
    geometry_sigma: np.ndarray          # NaN where not estimated
    aperture: np.ndarray
    aperture_sigma: np.ndarray
    a0: float
    a0_sigma: float
    offset_rad: float
    offset_sigma_rad: float
    noise_sigma: float                  # re-estimated from the residuals, counts
    residual_rms: float
    temperature_scale: float | None = None
    temperature_scale_sigma: float | None = None
    gain: np.ndarray | None = None
    gain_sigma: np.ndarray | None = None


@dataclass
class Estimate:
    """A solved calibration: values, per-variable sigmas (scaled by the residual noise level)."""

    code_l: int
    edges_rad: np.ndarray
    edges_sigma_rad: np.ndarray
    beta_rad: np.ndarray                # (N,) NaN where not used
    beta_sigma_rad: np.ndarray
    arrays: list[ArrayEstimate]
    values: gtsam.Values
    graph: gtsam.NonlinearFactorGraph
    model: EncoderModel
    factor_frames: list[tuple[int, int]]       # (array, J) of each frame factor, in graph order
    eccentricity: np.ndarray | None = None
    eccentricity_sigma: np.ndarray | None = None
    reference_offset_rad: float | None = None
    reference_offset_sigma_rad: float | None = None
    iterations: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    calibration_covariance: np.ndarray | None = None   # joint, order: edges 1..E-1, then per array globals
    covariance_layout: list[tuple[str, int]] = field(default_factory=list)


# --- graph assembly ----------------------------------------------------------------------------------------------

def _frame_constants(arr: ArrayData, code: enc.Code, beta: float, edge_alpha: np.ndarray, geometry: np.ndarray,
                     aperture: np.ndarray, illumination: np.ndarray, a0: float, offset: float, temperature_dev=0.0,
                     gain=None):
    """Edges of the bars touching the array at ``beta`` and the frame's constants."""
    b = beta + offset
    margin = 2.0 * aperture[1] + 0.02
    edges, alpha = enc.visible_bars(code, b, geometry, edge_alpha, margin_s=margin)
    s_e = enc.image_coordinate(alpha, b, geometry).s
    active = np.abs(s_e) < 1.0 + aperture[1] + 0.01
    wrap = alpha - edge_alpha[edges]
    const = fenc.FrameConstants(enc.diode_centres(arr.n), enc.edge_weights(code, edges, geometry),
                                edge_alpha[edges].copy(), wrap, geometry.copy(), aperture.copy(),
                                illumination.copy(), float(a0), offset, arr.kappa, temperature_dev, gain)
    return edges, active, const


def _start_illumination(frame: np.ndarray, a0: float, degree: int) -> np.ndarray:
    c = np.zeros(degree + 1)
    c[0] = max(np.percentile(frame, 95) - a0, 1.0)
    return c


@dataclass
class _Layout:
    frames: list[tuple[int, int]]
    edge_vars: set
    temperature_ref: float = 0.0


def build_graph(problem: Problem, model: EncoderModel, values: gtsam.Values, edge_alpha: np.ndarray,
                frames: list[tuple[int, int]] | None = None, gauge_edge: int = 0, term_columns: dict | None = None):
    """The factor graph at the current ``values`` (used to pick each frame's edges); returns graph, layout.

    ``frames``: (array, J) pairs to include (default: every decoded frame); ``term_columns``: per (array, J) the
    audit's generic terms, ``[(key, phi over the frame's diodes)]`` (:func:`selfcal.factors.encoder.frame_factor`).
    """
    term_columns = term_columns or {}
    code = problem.code
    graph = gtsam.NonlinearFactorGraph()
    if frames is None:
        frames = [(k, J) for k in range(len(problem.arrays)) for J in range(problem.n_positions)
                  if problem.decoded[k][J].ok and np.isfinite(problem.beta0[J])]
    edge_vars = set()
    temps = [a.temperature_degC for a in problem.arrays if a.temperature_degC is not None]
    t_ref = float(np.mean(np.concatenate(temps))) if temps else 0.0
    for k, J in frames:
        arr = problem.arrays[k]
        geometry = arr.geometry_nominal.copy()
        if values.exists(GEOMETRY(k)):
            geometry[list(model.geometry_free)] = values.atVector(GEOMETRY(k))
        aperture = values.atVector(APERTURE(k))
        offset = values.atVector(OFFSET(k))[0] if values.exists(OFFSET(k)) else arr.offset_nominal_rad
        beta = values.atVector(B(J))[0]
        t_dev = (arr.temperature_degC[J] - t_ref) if (model.temperature_scale and arr.temperature_degC is not None) else 0.0
        edges, active, const = _frame_constants(arr, code, beta, edge_alpha, geometry, aperture,
                                                values.atVector(ILLUMINATION(k, J)), values.atVector(A0(k))[0],
                                                offset, t_dev)
        edge_keys = []
        for e, act in zip(edges, active):
            variable = act and e != gauge_edge and not model.edges_fixed
            edge_keys.append(EDGE(int(e)) if variable else None)
            if variable:
                edge_vars.add(int(e))
        keys = fenc.FrameKeys(
            beta=B(J), edges=tuple(edge_keys),
            geometry=GEOMETRY(k) if values.exists(GEOMETRY(k)) else None, geometry_free=model.geometry_free,
            aperture=APERTURE(k), illumination=ILLUMINATION(k, J), a0=A0(k),
            offset=OFFSET(k) if k > 0 else None,
            eccentricity=ECCENTRICITY if model.eccentricity else None,
            temperature=TEMPERATURE(k) if model.temperature_scale else None,
            gain=GAIN(k) if model.prnu else None)
        noise = gtsam.noiseModel.Isotropic.Sigma(arr.n, arr.noise_sigma)
        graph.add(fenc.frame_factor(noise, arr.frames[J], keys, const, term_columns.get((k, J), ())))
    n_frame_factors = graph.size()
    for e in sorted(edge_vars):
        graph.add(gtsam.PriorFactorVector(EDGE(e), np.array([code.nominal_edge_angles()[e]]),
                                          gtsam.noiseModel.Isotropic.Sigma(1, EDGE_PRIOR_RAD)))
    if model.prnu:
        for k, arr in enumerate(problem.arrays):
            P = enc.illumination_basis(enc.diode_centres(arr.n), arr.illumination_degree)
            graph.add(fenc.linear_constraint_factor(gtsam.noiseModel.Isotropic.Sigma(P.shape[1], 1e-6), GAIN(k),
                                                    P.T / arr.n))
    ref = problem.reference
    if ref is not None:
        noise = gtsam.noiseModel.Isotropic.Sigma(1, ref.sigma_rad)
        for J, angle in zip(ref.positions, ref.angle_rad):
            if values.exists(B(int(J))):
                graph.add(_reference_factor(noise, float(angle), B(int(J))))
    assert n_frame_factors == len(frames)
    return graph, _Layout(frames, edge_vars, t_ref)


def _reference_factor(noise, angle_rad: float, beta_key: int) -> gtsam.CustomFactor:
    """``e = beta_J + c - angle_ref`` (wrapped to (-pi, pi]): a reference angle with its own zero ``c``."""

    def error(this, values, H):
        if H is not None:
            H[0] = np.ones((1, 1))
            H[1] = np.ones((1, 1))
        r = values.atVector(beta_key)[0] + values.atVector(REFERENCE_OFFSET)[0] - angle_rad
        return np.array([math.remainder(r, 2 * math.pi)])

    return gtsam.CustomFactor(noise, [beta_key, REFERENCE_OFFSET], error)


def initial_values(problem: Problem, model: EncoderModel, edge_alpha: np.ndarray | None = None,
                   beta0: np.ndarray | None = None, geometry: list[np.ndarray] | None = None) -> gtsam.Values:
    """Start values: positions from decoding (or given), edges nominal (or given), geometry nominal (or given)."""
    code = problem.code
    values = gtsam.Values()
    beta0 = problem.beta0 if beta0 is None else beta0
    for J in problem.used_positions():
        values.insert(B(int(J)), np.array([beta0[J]]))
    for k, arr in enumerate(problem.arrays):
        g = arr.geometry_nominal if geometry is None else geometry[k]
        if model.geometry_free:
            values.insert(GEOMETRY(k), np.asarray(g, dtype=float)[list(model.geometry_free)])
        values.insert(APERTURE(k), arr.aperture_nominal.copy())
        a0 = float(np.median(np.percentile(arr.frames, 2, axis=1)))
        values.insert(A0(k), np.array([a0]))
        if k > 0:
            values.insert(OFFSET(k), np.array([arr.offset_nominal_rad]))
        if model.temperature_scale:
            values.insert(TEMPERATURE(k), np.zeros(1))
        if model.prnu:
            values.insert(GAIN(k), np.zeros(arr.n))
        for J in problem.used_positions():
            if problem.decoded[k][J].ok:
                values.insert(ILLUMINATION(k, int(J)),
                              _start_illumination(arr.frames[J], a0, arr.illumination_degree))
    if model.eccentricity:
        values.insert(ECCENTRICITY, np.zeros(2))
    if problem.reference is not None:
        ref = problem.reference
        c0 = [math.remainder(a - beta0[J], 2 * math.pi) for J, a in zip(ref.positions, ref.angle_rad)
              if np.isfinite(beta0[J])]
        values.insert(REFERENCE_OFFSET, np.array([float(np.median(c0)) if c0 else 0.0]))
    return values


def insert_edges(values: gtsam.Values, edge_vars, edge_alpha: np.ndarray) -> None:
    for e in sorted(edge_vars):
        if not values.exists(EDGE(e)):
            values.insert(EDGE(e), np.array([edge_alpha[e]]))


def edge_angles(values: gtsam.Values, code: enc.Code, default: np.ndarray | None = None) -> np.ndarray:
    alpha = code.nominal_edge_angles().copy() if default is None else np.array(default, dtype=float)
    for e in range(code.n_edges):
        if values.exists(EDGE(e)):
            alpha[e] = values.atVector(EDGE(e))[0]
    return alpha


def optimize(graph, values, max_iterations: int = 50) -> tuple[gtsam.Values, int]:
    """Levenberg-Marquardt with GTSAM's sparse multifrontal Cholesky (COLAMD ordering)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-9)
    params.setAbsoluteErrorTol(1e-9)
    params.setLinearSolverType("MULTIFRONTAL_CHOLESKY")
    params.setOrderingType("COLAMD")
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    if optimizer.iterations() == 0 and graph.error(values) > 0.0:
        # no step accepted at all: with lambda I the first steps of a badly scaled start (edges in rad next to
        # gains and a temperature scale per degC) all raised the error until lambda hit its bound, and the start
        # came back as the "solution" (an audit seed: 489.7 -> 489.7).  Marquardt's damping, lambda diag(J^T J),
        # scales each variable by its own curvature (the same seed: 489.7 -> 104 in 13 iterations)
        params.setDiagonalDamping(True)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = optimizer.optimize()
    log.info("LM: error %.6g -> %.6g in %d iterations", graph.error(values), graph.error(result),
             optimizer.iterations())
    return result, int(optimizer.iterations())


# --- batch calibration -------------------------------------------------------------------------------------------

def residuals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n_frames: int) -> list[np.ndarray]:
    """Unwhitened residual vector (counts) of each frame factor (the first ``n_frames`` factors)."""
    return [graph.at(i).unwhitenedError(values) for i in range(n_frames)]


def calibrate(problem: Problem, model: EncoderModel = EncoderModel(), max_iterations: int = 50,
              covariance: bool = True, start: dict | None = None) -> Estimate:
    """Batch ML self-calibration: positions, edges, per-array geometry/aperture/a0/offset, with sigmas.

    Two passes: the first at the decoded start values; the graph is then rebuilt at the solution (so each
    frame holds exactly the edges it sees) and solved again.  ``start`` may hold ``edges``, ``beta`` and
    ``geometry`` (list per array) from another estimator (e.g. the patent baseline).
    """
    t_start = time.perf_counter()
    code = problem.code
    if problem.used_positions().size < 2:
        raise DegenerateDataError("fewer than two decodable frames: nothing to calibrate")
    start = start or {}
    edge_alpha = np.asarray(start.get("edges", code.nominal_edge_angles()), dtype=float)
    values = initial_values(problem, model, edge_alpha, start.get("beta"), start.get("geometry"))
    iterations = 0
    graph, layout = build_graph(problem, model, values, edge_alpha)
    for _ in range(3):
        insert_edges(values, layout.edge_vars, edge_alpha)
        values, it = optimize(graph, values, max_iterations)
        iterations += it
        edge_alpha = edge_angles(values, code, edge_alpha)
        signature = _edge_sets(graph, layout)
        graph, layout = build_graph(problem, model, values, edge_alpha)
        if _edge_sets(graph, layout) == signature:
            break   # every frame holds exactly the edges it sees at the solution
    est = _estimate(problem, model, graph, layout, values, edge_alpha, covariance)
    est.iterations = iterations
    est.seconds = time.perf_counter() - t_start
    return est


def _weak_links(problem, graph, layout) -> list[float]:
    """Positions (rad) where neighbouring frames of array 0 share fewer than two edge variables."""
    frames = [(i, J) for i, (k, J) in enumerate(layout.frames) if k == 0]
    if len(frames) < 3:
        return []
    beta = np.array([problem.beta0[J] for _, J in frames])
    order = np.argsort(beta)
    edge_sets = [{key for key in graph.at(i).keys() if gtsam.Symbol(key).chr() == ord("e")} for i, _ in frames]
    weak = []
    for a, b in zip(order, np.roll(order, -1)):
        if len(edge_sets[a] & edge_sets[b]) < 2:
            weak.append(float(beta[a]))
    return weak


def _edge_sets(graph, layout) -> list[tuple[int, ...]]:
    return [tuple(graph.at(i).keys()) for i in range(len(layout.frames))]


def _noise_levels(problem, graph, layout, values) -> dict[int, tuple[float, float]]:
    """Per array: (re-estimated noise sigma (counts), residual RMS) from the frame residuals."""
    res = residuals(graph, values, len(layout.frames))
    n_params = values.dim()
    n_obs = sum(r.size for r in res)
    dof_factor = n_obs / max(n_obs - n_params, 1)
    out = {}
    for k in range(len(problem.arrays)):
        r = np.concatenate([res[i] for i, (kk, _) in enumerate(layout.frames) if kk == k])
        rms = float(np.sqrt(np.mean(r**2)))
        out[k] = (rms * math.sqrt(dof_factor), rms)
    return out


def _estimate(problem, model, graph, layout, values, edge_alpha, covariance: bool) -> Estimate:
    code = problem.code
    levels = _noise_levels(problem, graph, layout, values)
    # the graph was built with the sensor.yaml sigmas: rebuild with the estimated ones for the covariance
    for k, arr in enumerate(problem.arrays):
        arr.noise_sigma = levels[k][0]
    graph, layout = build_graph(problem, model, values, edge_alpha, layout.frames)
    positions = sorted({J for _, J in layout.frames})  # the solved frames' (all used ones, or a subset)
    keys_sigma = [B(int(J)) for J in positions]
    if not covariance:
        keys_sigma += [EDGE(e) for e in sorted(layout.edge_vars)]
    for k in range(len(problem.arrays)):
        keys_sigma += [key for key in (GEOMETRY(k), APERTURE(k), A0(k), OFFSET(k), TEMPERATURE(k), GAIN(k))
                       if values.exists(key)]
    for key in (ECCENTRICITY, REFERENCE_OFFSET):
        if values.exists(key):
            keys_sigma.append(key)
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as err:
        raise DegenerateDataError(f"the frames do not determine the calibration (singular information: {err})") \
            from None
    cov = {key: marginals.marginalCovariance(key) for key in keys_sigma}
    sig = lambda key: np.sqrt(np.diag(cov[key])) if key in cov else None  # noqa: E731
    N = problem.n_positions
    beta = np.full(N, np.nan)
    beta_sigma = np.full(N, np.nan)
    for J in positions:
        beta[J] = values.atVector(B(int(J)))[0]
        beta_sigma[J] = sig(B(int(J)))[0]
    edges_sigma = np.zeros(code.n_edges)
    edges_sigma[:] = np.nan
    edges_sigma[0] = 0.0
    joint, layout_keys = None, []
    if covariance:   # one joint marginal of edges and array parameters: the edges' sigmas are its diagonal
        layout_keys = [("edge", e) for e in sorted(layout.edge_vars)]
        for k in range(len(problem.arrays)):
            layout_keys += [(name, k) for name, key in (("geometry", GEOMETRY(k)), ("aperture", APERTURE(k)),
                                                        ("a0", A0(k)), ("offset", OFFSET(k)))
                            if values.exists(key)]
        joint = joint_covariance(marginals, [_key_of(name, i) for name, i in layout_keys])
        for i, e in enumerate(sorted(layout.edge_vars)):
            edges_sigma[e] = math.sqrt(joint[i, i])
    else:
        for e in layout.edge_vars:
            edges_sigma[e] = sig(EDGE(e))[0]
    arrays = []
    for k, arr in enumerate(problem.arrays):
        geometry = arr.geometry_nominal.copy()
        g_sigma = np.full(6, np.nan)
        if values.exists(GEOMETRY(k)):
            geometry[list(model.geometry_free)] = values.atVector(GEOMETRY(k))
            g_sigma[list(model.geometry_free)] = sig(GEOMETRY(k))
        est = ArrayEstimate(
            geometry, g_sigma, values.atVector(APERTURE(k)), sig(APERTURE(k)), float(values.atVector(A0(k))[0]),
            float(sig(A0(k))[0]), float(values.atVector(OFFSET(k))[0]) if k else 0.0,
            float(sig(OFFSET(k))[0]) if k else 0.0, levels[k][0], levels[k][1])
        if values.exists(TEMPERATURE(k)):
            est.temperature_scale = float(values.atVector(TEMPERATURE(k))[0])
            est.temperature_scale_sigma = float(sig(TEMPERATURE(k))[0])
        if values.exists(GAIN(k)):
            est.gain, est.gain_sigma = values.atVector(GAIN(k)), sig(GAIN(k))
        arrays.append(est)
    out = Estimate(code.l, edge_alpha.copy(), edges_sigma, beta, beta_sigma, arrays, values, graph, model,
                   layout.frames)
    if values.exists(ECCENTRICITY):
        out.eccentricity, out.eccentricity_sigma = values.atVector(ECCENTRICITY), sig(ECCENTRICITY)
    if values.exists(REFERENCE_OFFSET):
        out.reference_offset_rad = float(values.atVector(REFERENCE_OFFSET)[0])
        out.reference_offset_sigma_rad = float(sig(REFERENCE_OFFSET)[0])
    weak = _weak_links(problem, graph, layout)
    if weak:
        out.notes.append(f"{len(weak)} pairs of neighbouring positions share fewer than 2 edges (the relative angle "
                         "across them rests on the geometry alone; add positions or image more cells): near "
                         + ", ".join(f"{b:.3f} rad" for b in weak[:8]))
    missing = [e for e in range(1, code.n_edges) if e not in layout.edge_vars]
    if missing and not model.edges_fixed:
        out.notes.append(f"{len(missing)} edges never seen on the array (kept nominal, sigma NaN): "
                         f"{missing[:10]}{' ...' if len(missing) > 10 else ''}")
    if joint is not None:
        out.calibration_covariance, out.covariance_layout = joint, layout_keys
    return out


def _key_of(name: str, i: int) -> int:
    return {"edge": EDGE, "geometry": GEOMETRY, "aperture": APERTURE, "a0": A0, "offset": OFFSET}[name](i)


def joint_covariance(marginals: gtsam.Marginals, keys: list[int]) -> np.ndarray:
    """Joint marginal covariance of ``keys`` (GTSAM's Bayes-tree joint marginal), as one dense matrix."""
    kv = gtsam.KeyVector()
    for key in keys:
        kv.append(key)
    joint = marginals.jointMarginalCovariance(kv)
    return joint.fullMatrix()


# --- measurement with a calibration --------------------------------------------------------------------------

RESIDUAL_FLAG_SIGMAS = 6.0   # whitened RMS above 1 + 6 sqrt(2/n): the frame does not fit the model


@dataclass
class ArrayCalibration:
    """What measuring needs of one array: its calibrated parameters and their joint covariance indices."""

    geometry: np.ndarray
    geometry_free: tuple[int, ...]
    aperture: np.ndarray
    a0: float
    offset_rad: float
    noise_sigma: float
    illumination_degree: int = 2
    adc_max: float | None = None
    cov_index: dict = field(default_factory=dict)   # "geometry"/"aperture"/"a0"/"offset" -> indices into cov


@dataclass
class Measurement:
    beta_rad: float
    sigma_rad: float
    sigma_noise_rad: float
    flag: str
    residual_rms: float = float("nan")      # whitened


def measure_frame(frame: np.ndarray, code: enc.Code, edges_rad: np.ndarray, cal: ArrayCalibration,
                  covariance: np.ndarray | None = None, edge_cov_index: dict | None = None) -> Measurement:
    """ML angle of one new frame with the calibration held fixed: (beta, illumination) by GTSAM's LM.

    The 1-sigma combines the frame's own noise (marginal of beta with the calibration's noise level) and the
    calibration's uncertainty carried through the implicit function ``beta_hat(theta)``:
    ``d x_hat / d theta = -(J_x^T J_x)^-1 J_x^T J_theta`` for the calibrated parameters ``theta`` the frame
    depends on (its edges, geometry, aperture, a0), with their joint covariance from the calibration.
    Flags: the decoder's (saturated, dark, undecodable, code_mismatch), ``residual`` when the fit leaves a
    whitened RMS above ``1 + 6 sqrt(2/n)`` (a dirty disk, a wrong window), ``jump`` when the fit moved more
    than a quarter cell from the decoded start.
    """
    frame = np.asarray(frame, dtype=float)
    n = frame.size
    dec = enc.decode_frame(frame, code, cal.geometry, edges_rad, adc_max=cal.adc_max, noise_sigma=cal.noise_sigma)
    if not dec.ok:
        return Measurement(float("nan"), float("nan"), float("nan"), dec.flag)
    beta0 = dec.beta_rad - cal.offset_rad
    const_edges, active, const = _frame_constants(
        ArrayData("measure", frame[None, :], cal.geometry, cal.aperture), code, beta0, edges_rad, cal.geometry,
        cal.aperture, _start_illumination(frame, cal.a0, cal.illumination_degree), cal.a0, cal.offset_rad)
    keys = fenc.FrameKeys(beta=B(0), edges=tuple(None for _ in const_edges), illumination=ILLUMINATION(0, 0))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(fenc.frame_factor(gtsam.noiseModel.Isotropic.Sigma(n, cal.noise_sigma), frame, keys, const))
    values = gtsam.Values()
    values.insert(B(0), np.array([beta0]))
    values.insert(ILLUMINATION(0, 0), const.illumination.copy())
    values, _ = optimize(graph, values, 30)
    beta = values.atVector(B(0))[0]
    r = graph.at(0).whitenedError(values)
    rms = float(np.sqrt(np.mean(r**2)))
    # Jacobians at the solution: x = (beta, illumination), theta = calibrated parameters
    alpha = const.edge_alpha_rad + const.edge_wrap_rad
    _, jac = enc.frame_signal(const.s_diodes, alpha, const.weights, beta + cal.offset_rad, cal.geometry,
                              cal.aperture, values.atVector(ILLUMINATION(0, 0)), cal.a0)
    Jx = np.column_stack([jac.d_beta, jac.d_illumination])
    Nx = Jx.T @ Jx
    Nx_inv = np.linalg.inv(Nx)
    sigma_noise = cal.noise_sigma * math.sqrt(Nx_inv[0, 0])
    var = sigma_noise**2
    if covariance is not None and edge_cov_index is not None:
        cols, idx = [], []
        for i, e in enumerate(const_edges):
            if active[i] and int(e) in edge_cov_index:
                cols.append(jac.d_alpha[:, i])
                idx.append(edge_cov_index[int(e)])
        for name, block in (("geometry", jac.d_geometry[:, list(cal.geometry_free)]), ("aperture", jac.d_aperture),
                            ("a0", jac.d_a0[:, None]), ("offset", jac.d_beta[:, None])):
            if name in cal.cov_index:
                cols.extend(block.T)
                idx.extend(cal.cov_index[name])
        if cols:
            Jt = np.column_stack(cols)
            g = -(Nx_inv @ (Jx.T @ Jt))[0]
            var += float(g @ covariance[np.ix_(idx, idx)] @ g)
    flag = enc.FLAG_OK
    if rms > 1.0 + RESIDUAL_FLAG_SIGMAS * math.sqrt(2.0 / n):
        flag = "residual"
    elif abs(math.remainder(beta - beta0, 2 * math.pi)) > 0.25 * code.cell_rad:
        flag = "jump"
    return Measurement(float(np.remainder(beta, 2 * math.pi)), math.sqrt(var), sigma_noise, flag, rms)


def array_calibration(est: Estimate, problem: Problem, k: int = 0) -> tuple[ArrayCalibration, dict]:
    """Measuring view of array k of a solved calibration, and the edge -> covariance index map."""
    a = est.arrays[k]
    arr = problem.arrays[k]
    cov_index, edge_index = {}, {}
    for i, (name, idx) in enumerate(est.covariance_layout):
        if name == "edge":
            edge_index[idx] = i
    offset = 0
    for name, idx in est.covariance_layout:
        dim = {"edge": 1, "geometry": len(est.model.geometry_free), "aperture": 2, "a0": 1, "offset": 1}[name]
        if name != "edge" and idx == k:
            cov_index[name] = list(range(offset, offset + dim))
        offset += dim
    return ArrayCalibration(a.geometry, est.model.geometry_free, a.aperture, a.a0, a.offset_rad, a.noise_sigma,
                            arr.illumination_degree, arr.adc_max, cov_index), edge_index


# --- observability of the eccentricity -------------------------------------------------------------------------

ECCENTRICITY_INFORMATION_FLOOR = 0.01   # fraction of its own information the eccentricity must keep: below it
# (a correlation above 0.995 with the other unknowns) only second-order terms (q s) separate it, and any
# unmodelled distortion of the image would alias into the estimate


@dataclass
class Observability:
    observable: bool
    information_fraction: float      # smallest eigenvalue of the Schur complement / of its own block (scaled)
    sigma: np.ndarray                # 1-sigma of (eps_x, eps_y), code radii (inf when singular)
    reason: str


def eccentricity_observability(problem: Problem, est: Estimate) -> Observability:
    """Can the data separate the code's eccentricity from the edges, geometry and positions?

    Linearises the graph with an eccentricity variable added at the solution and compares the information on
    it that survives the other unknowns (the Schur complement ``S = H_ee - H_eo H_oo^-1 H_oe``) with the
    information it has alone (``H_ee``).  A fraction below 1 % means the eccentricity's signature is almost a
    combination of the others': with free edges it is a once-per-revolution graduation error but for the
    ``(1 + q s)`` factor of formula (0), so it is reported unobservable.
    A dense analysis of the linearised system (a diagnostic for this one question, not the solver).
    """
    model = EncoderModel(est.model.geometry_free, True, est.model.temperature_scale, est.model.prnu,
                         est.model.edges_fixed)
    values = gtsam.Values(est.values)
    if not values.exists(ECCENTRICITY):
        values.insert(ECCENTRICITY, np.zeros(2))
    graph, _ = build_graph(problem, model, values, est.edges_rad, est.factor_frames)
    ordering = gtsam.Ordering()
    keys = [k for k in values.keys() if k != ECCENTRICITY] + [ECCENTRICITY]
    for k in keys:
        ordering.push_back(k)
    H, _ = graph.linearize(values).hessian(ordering)
    H = np.array(H)
    H_oo, H_oe, H_ee = H[:-2, :-2], H[:-2, -2:], H[-2:, -2:]
    scale = np.sqrt(np.diag(H_oo))
    Hs = H_oo / np.outer(scale, scale)
    S = H_ee - H_oe.T @ (np.linalg.solve(Hs, H_oe / scale[:, None]) / scale[:, None])
    own = np.linalg.eigvalsh(H_ee)
    remaining = np.linalg.eigvalsh(0.5 * (S + S.T))
    fraction = float(max(remaining[0], 0.0) / own[-1]) if own[-1] > 0 else 0.0
    observable = fraction > ECCENTRICITY_INFORMATION_FLOOR
    sigma = np.sqrt(np.diag(np.linalg.inv(S))) if observable else np.full(2, np.inf)
    arrays = len(problem.arrays)
    reason = (f"{arrays} array(s): the eccentricity keeps {fraction:.2g} of its information next to the other "
              "unknowns" + ("" if observable else
                            " -- its signature is a once-per-revolution graduation error, which the free edges "
                            "absorb: unobservable"))
    return Observability(observable, fraction, sigma, reason)
