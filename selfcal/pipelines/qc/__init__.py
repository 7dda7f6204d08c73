"""``selfcal qc`` (quality control of a scan) and the qc audit (one sphere in several scenes)."""


def audit_system(recording, base: str = "sphere", sensors: list[str] | None = None):
    """The audit's view of a sphere-scans recording (:mod:`selfcal.pipelines.qc.audit`)."""
    from selfcal.pipelines.qc.audit import sphere_scans_audit
    return sphere_scans_audit(recording, sensors)
