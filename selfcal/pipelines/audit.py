"""Use case ``selfcal audit``: fit the base model, search the catalog, measure against simulation, report.

The system is found by name in :mod:`selfcal.registry`; its pipeline module builds the audit system from the
recording (``audit_system(recording, base, sensors)``), and the engine (:mod:`selfcal.audit.engine`) is the same
for every system.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from selfcal import registry
from selfcal.audit.engine import AuditResult, run_audit
from selfcal.core.errors import SelfcalError
from selfcal.core.progress import quiet
from selfcal.io.recording import Recording
from selfcal.pipelines.fleet import FleetError, register_task

log = logging.getLogger(__name__)


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

            from selfcal.audit.report import allan_table, plot_allan
            folder = Path(figure_dir or tempfile.mkdtemp(prefix="selfcal-allan-"))
            extras["noise"] = [{
                "title": f"Allan deviation of {n.sensor}/{n.quantity}: measured against the white-noise model "
                         f"and the extended one ({'accepted' if n.finding else 'not accepted'})",
                "png_path": str(plot_allan(n, folder / f"allan_{n.sensor}_{n.quantity}.png")),
                "table": allan_table(n)} for n in self.noise]
        return extras


def audit_recording(recording: Recording, system: str, base: str | None = None, sensors: list[str] | None = None,
                    progress=quiet, simulate_seed: int = 1) -> AuditRun:
    """Audit a recording as ``system`` (any system of :mod:`selfcal.registry` with an audit) against ``base``
    (default: the system's first base model); ``sensors`` picks the IMU(s) where a system uses IMUs.
    ``progress(stage)`` is told each stage as it starts (:mod:`selfcal.core.progress`)."""
    entry = registry.system(system)
    if not entry.audit:
        raise registry.UnknownSystemError(f"system {system!r} has no audit; audited systems: "
                                          f"{', '.join(registry.names('audit'))}")
    base = base or entry.audit[0]
    if base not in entry.audit:
        raise SelfcalError(f"unknown base model {base!r} for system {system}: choose {' or '.join(entry.audit)}")
    progress(f"read the {system} recording and solve its {base} model")
    audit_system = entry.load("pipelines").audit_system(recording, base, sensors)
    result = run_audit(audit_system, progress=progress)
    # optional hooks of an audit system: model-free diagnostics, a re-simulation of the recording's own
    # scenario, and noise analyses beyond the residual search
    run = AuditRun(result, diagnostics=dict(getattr(audit_system, "diagnostics", {})))
    if hasattr(audit_system, "simulate"):
        progress("simulate the recording's scenario (measured vs simulated)")
        run.simulation = measured_vs_simulated(audit_system, result, simulate_seed)
    if hasattr(audit_system, "noise_audits"):
        run.noise = audit_system.noise_audits(progress)
    return run


def measured_vs_simulated(system, result: AuditResult, seed: int) -> list[dict]:
    """Residual RMS per family and axis: measured vs the recording's scenario simulated with the base and final
    models.

    Both simulations are analysed with the base model as the measurement was: the base model's own simulation
    shows what it expects to leave; the final model's simulation shows whether the extension reproduces what
    the measurement really left.
    """
    base_effects, final_effects = result.base_fit.effects, result.final_effects
    sim_base = system.simulate(result.base_fit, seed, noise_fit=result.final_fit)
    sim_final = system.simulate(result.final_fit, seed, noise_fit=result.final_fit)
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


# --- fleet ------------------------------------------------------------------------------------------------------

def audit_task(recording_path, options: dict) -> dict:
    """``selfcal audit`` (option ``system``: any audited system; ``base``, ``imu``, ``imu1``) as columns.

    Columns: ``findings`` (count), ``effects`` (``effect@target`` in the order found), ``final_model``, and per
    residual family the RMS of the base model (``rms_before_<family>``) and of the final one (``rms_after_``).
    """
    from selfcal.io.recording import read_recording
    if not options.get("system"):
        raise FleetError(f"task audit needs the option system ({', '.join(registry.names('audit'))}): --system imu")
    rec = read_recording(recording_path)
    sensors = [options[k] for k in ("imu", "imu1") if options.get(k)] or None
    run = audit_recording(rec, options["system"], options.get("base"), sensors)
    contract = run.to_json()
    out = {"system": contract["system"], "base_model": contract["base_model"],
           "findings": len(contract["findings"]),
           "effects": "; ".join(f"{f['effect']}@{f.get('target', f.get('sensor', ''))}"
                                for f in contract["findings"]),
           "final_model": "; ".join(contract["final_model"])}
    for fam in run.result.base_fit.families:
        out[f"rms_before_{_column(fam.label)}"] = float(fam.rms)
    for fam in run.result.final_fit.families:
        out[f"rms_after_{_column(fam.label)}"] = float(fam.rms)
    return out


def _column(label: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in label).strip("_")


register_task("audit", audit_task, ("system", "base", "imu", "imu1"),
              "residual audit: findings, effect names, residual RMS before/after", required=("system",))
