"""Use case ``selfcal audit``: fit the base model, search the catalog, measure against simulation, report."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from selfcal.core import inertial
from selfcal.audit.engine import AuditResult, run_audit
from selfcal.audit.imu_pair import ImuPairAudit, simulate_pair_like
from selfcal.audit.imu.static import ImuStaticAudit
from selfcal.audit.noise import noise_audit
from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit, simulate_like
from selfcal.io.recording import Recording

log = logging.getLogger(__name__)

SYSTEMS = ("imu", "imu-pair", "encoder", "scan", "ship", "tracker")


@dataclass
class AuditRun:
    result: AuditResult
    simulation: list[dict] = field(default_factory=list)  # measured against simulated, per residual family
    noise: list = field(default_factory=list)  # NoiseAuditResult per quantity (static logs)
    diagnostics: dict = field(default_factory=dict)  # system-level diagnostics (e.g. the pair's correlation lag)

    def to_json(self) -> dict:
        out = self.result.to_json()
        noise_findings = [n.finding for n in self.noise if n.finding]
        out["findings"] = out["findings"] + noise_findings
        out["final_model"] = out["final_model"] + sorted({f["effect"] for f in noise_findings})
        if self.simulation:
            out["measured_vs_simulated"] = self.simulation
        if self.noise:
            out["noise"] = [{"sensor": n.sensor, "quantity": n.quantity, "axes": n.summary()} for n in self.noise]
        if self.diagnostics:
            out["diagnostics"] = self.diagnostics
        return out

    def report_extras(self, recording: str, figure_dir=None) -> dict:
        extras = {"recording": recording}
        if self.simulation:
            extras["simulation"] = self.simulation
        if self.noise:
            extras["noise_findings"] = [n.finding for n in self.noise if n.finding]
            import tempfile
            from pathlib import Path

            from selfcal.audit.noise import plot_allan
            folder = Path(figure_dir or tempfile.mkdtemp(prefix="selfcal-allan-"))
            extras["noise"] = [{
                "title": f"Allan deviation of {n.sensor}/{n.quantity}: measured against the white-noise model "
                         f"and the extended one ({'accepted' if n.finding else 'not accepted'})",
                "png_path": str(plot_allan(n, folder / f"allan_{n.sensor}_{n.quantity}.png")),
                "table": n.summary()} for n in self.noise]
        return extras


def audit_recording(recording: Recording, system: str, base: str | None = None, sensors: list[str] | None = None,
                    progress=None, simulate_seed: int = 1) -> AuditRun:
    """Audit one IMU (system ``imu``) or one pair of IMUs (``imu-pair``) of a recording."""
    names = sensors or recording.imu_names()
    if system == "imu":
        data = recording.imu(names[0])
        if is_static_log(data):
            if base not in (None, "bias"):
                raise ValueError(f"a static log is audited against the base model 'bias', not {base!r}")
            audit_system = ImuStaticAudit(data)
        else:
            audit_system = ImuIntrinsicsAudit(data, float(data.meta.get("gravity_m_s2", inertial.STANDARD_GRAVITY_M_S2)),
                                              base or "bias")
    elif system == "imu-pair":
        if len(names) < 2:
            raise ValueError(f"system imu-pair needs two IMUs, the recording has {names}")
        if base not in (None, "rotation"):
            raise ValueError(f"unknown base model {base!r} for system imu-pair: the base is 'rotation'")
        audit_system = ImuPairAudit(recording.imu(names[0]), recording.imu(names[1]))
    elif system == "encoder":
        if base not in (None, "ml"):
            raise ValueError(f"unknown base model {base!r} for system encoder: the base is 'ml'")
        from selfcal.pipelines.encoder import encoder_audit_system
        audit_system = encoder_audit_system(recording)
    elif system == "scan":
        if base not in (None, "error15"):
            raise ValueError(f"unknown base model {base!r} for system scan: the base is 'error15'")
        from selfcal.audit.scan import ScanAudit
        from selfcal.pipelines.scan import read_scan, scan_problem
        audit_system = ScanAudit(scan_problem(read_scan(recording)))
    elif system == "ship":
        if base not in (None, "attitude"):
            raise ValueError(f"unknown base model {base!r} for system ship: the base is 'attitude'")
        from selfcal.audit.ship import ShipAudit
        from selfcal.pipelines.ship import ship_inputs
        name = names[0] if names else "imu0"
        audit_system = ShipAudit(ship_inputs(recording, name), sensor=name)
    elif system == "tracker":
        if base not in (None, "smoother"):
            raise ValueError(f"unknown base model {base!r} for system tracker: the base is 'smoother'")
        from selfcal.audit.tracker import TrackerAudit
        from selfcal.pipelines.tracker import estimator_for_audit
        audit_system = TrackerAudit(estimator_for_audit(recording))
    else:
        raise ValueError(f"unknown system {system!r}; known: {', '.join(SYSTEMS)}")
    result = run_audit(audit_system, progress=progress)
    run = AuditRun(result)
    if system == "encoder":
        run.diagnostics.update(audit_system.diagnostics)
    if isinstance(audit_system, ImuPairAudit):
        run.diagnostics["cross_correlation_lag_s"] = {
            "value": audit_system.initial_dt_s,
            "meaning": "delay maximising the correlation of |w| of the two IMUs (rotation-invariant): the "
                       "model-free estimate of t_imu0 - t_imu1, to compare with a time_offset finding"}
    if isinstance(audit_system, (ImuIntrinsicsAudit, ImuPairAudit)):
        if isinstance(audit_system, ImuIntrinsicsAudit):
            simulate = simulate_like  # noise from the static samples' own scatter
        else:  # the pair has no independent noise level: the final model's residual is its best estimate
            simulate = partial(simulate_pair_like, noise_fit=result.final_fit)
        run.simulation = measured_vs_simulated(audit_system, result, simulate, simulate_seed)
    if isinstance(audit_system, ImuStaticAudit) and data.t_s[-1] >= NOISE_AUDIT_MIN_S:
        for quantity, samples, key in (("gyro", data.gyro_rad_s, "gyroscope_noise_density"),
                                       ("accel", data.accel_m_s2, "accelerometer_noise_density")):
            if progress:
                progress(f"Allan analysis of {data.name}/{quantity}")
            run.noise.append(noise_audit(samples, data.rate_hz, quantity, sensor=data.name))
    return run


STATIC_LOG_MAX_TILT_DEG = 2.0
NOISE_AUDIT_MIN_S = 300.0  # Allan analysis needs taus of minutes to see a bias wander


def is_static_log(data) -> bool:
    """One orientation throughout: the gravity direction of 1 s means never leaves a 2 deg cone."""
    n = max(1, int(round(data.rate_hz)))
    m = len(data.accel_m_s2) // n
    if m < 10:
        return False
    means = data.accel_m_s2[:m * n].reshape(m, n, 3).mean(axis=1)
    directions = means / np.linalg.norm(means, axis=1, keepdims=True)
    mean = directions.mean(axis=0)
    cos = directions @ (mean / np.linalg.norm(mean))
    return bool(np.degrees(np.arccos(np.clip(cos.min(), -1, 1))) < STATIC_LOG_MAX_TILT_DEG)


def measured_vs_simulated(system, result: AuditResult, simulate, seed: int) -> list[dict]:
    """Residual RMS per family and axis: measured vs the recording's scenario simulated with the base and final
    models.

    Both simulations are analysed with the base model as the measurement was: the base model's own simulation
    shows what it expects to leave; the final model's simulation shows whether the extension reproduces what
    the measurement really left.
    """
    base_effects, final_effects = result.base_fit.effects, result.final_effects
    sim_base = simulate(system, result.base_fit, seed)
    sim_final = simulate(system, result.final_fit, seed)
    columns = {"measured_base_fit": result.base_fit,
               "simulated_base_model_base_fit": sim_base.fit(base_effects),
               "simulated_final_model_base_fit": sim_final.fit(base_effects),
               "measured_final_fit": result.final_fit,
               "simulated_final_model_final_fit": sim_final.fit(final_effects)}
    table = []
    for fam in result.base_fit.families:
        axes = ["|f| - g"] if fam.physical.shape[1] == 1 else ["x", "y", "z"][:fam.physical.shape[1]]
        for j, axis in enumerate(axes):
            row = {"family": fam.label, "axis": axis, "unit": fam.unit}
            for name, fit in columns.items():
                other = fit.family(fam.quantity, fam.sensor)
                row[name] = float(np.sqrt(np.mean(other.physical[:, j] ** 2))) if other is not None else None
            table.append(row)
    return table
