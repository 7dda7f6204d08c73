"""The qc audit: one sphere target scanned by a LiDAR in several scenes (``selfcal audit --system qc``).

The factor (range residual of each return on a sphere, :mod:`selfcal.models.qc`) is checked for exact zero on
noise-free returns, Jacobians at random points and, by Monte Carlo over seeds, for radius estimates whose scatter
matches the covariance the graph reports (its Cramér–Rao bound for this model).  The audit then meets simulated
scans hiding one effect each, told nothing: the catalog's ``sphere_radius`` and ``range_offset``, a radius that
changes with range and a range error growing with incidence (neither in the catalog), the range offset's
look-alike, and nulls (with and without a scene-to-scene radius scatter).  Tolerances: 3 reported sigma
(two-sided 99.7 %); the Monte Carlo variance ratio within the chi-square 99.9 % interval of its seeds.
"""
from __future__ import annotations

import gzip
import hashlib
import json
from pathlib import Path

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from factor_checks import assert_factor_jacobians
from selfcal.audit.engine import run_audit
from selfcal.audit.qc import SphereScansAudit
from selfcal.cli.main import main
from selfcal.factors.qc import sphere_returns_factor
from selfcal.graphs import qc as gq
from selfcal.models.qc import MAX_INCIDENCE_RAD
from selfcal.sim.qc import LidarSphereScenes
from shared_data import SHARED_DATA

SHARED = SHARED_DATA / "spherecalib_lidar_2cam_sphere"
SHIPPED = Path(__file__).resolve().parents[1] / "data" / "spherecalib_lidar"
NOMINAL_M = 0.3


def scans_of(sim: LidarSphereScenes, seed: int) -> gq.SphereScans:
    return gq.scans_of("lidar0", [gq.scene_of(p, t_s=float(i)) for i, p in enumerate(sim.scenes(seed))], NOMINAL_M)


def audit(sim: LidarSphereScenes, seed: int) -> dict:
    return run_audit(SphereScansAudit(scans_of(sim, seed))).to_json()


def names(contract) -> list[str]:
    return [f["effect"] if f["effect"] != "unlisted" else f"unlisted:{f['driver']}" for f in contract["findings"]]


def the(contract, effect) -> dict:
    hits = [f for f in contract["findings"] if f["effect"] == effect]
    assert len(hits) == 1, names(contract)
    return hits[0]


def within_3_sigma(value, sigma, truth) -> bool:
    return abs(value - truth) <= 3.0 * sigma


# --- the factor -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(3))
def test_factor_exact_zero_and_jacobians(seed):
    rng = np.random.default_rng(seed)
    sim = LidarSphereScenes(range_noise_m=0.0, range_offset_m=0.02, ranges_m=(2.0,))
    points, centre = sim.scenes(seed)[0], sim.centres_m(seed)[0]
    phi = rng.normal(size=len(points))
    factor = sphere_returns_factor(gtsam.noiseModel.Isotropic.Sigma(len(points), 0.005), points, 1, 0.25,
                                   radius_keys=[2], range_offset_key=3, term_columns=[(4, phi)])
    exact = {1: centre, 2: np.array([0.05]), 3: np.array([0.02]), 4: np.array([0.0])}
    values = gtsam.Values()
    for key, value in exact.items():
        values.insert(key, value)
    assert np.max(np.abs(factor.unwhitenedError(values))) < 1e-12
    assert_factor_jacobians(factor, {1: centre + 0.01 * rng.normal(size=3), 2: 0.01 * rng.normal(size=1),
                                     3: 0.01 * rng.normal(size=1), 4: 1e-3 * rng.normal(size=1)}, delta=1e-7,
                            atol=1e-5)


def test_radius_estimates_scatter_as_the_reported_sigma_says():
    """Monte Carlo over 20 seeds: z = (dR - truth) / sigma has mean square in the chi-square 99.9 % interval."""
    seeds, truth = range(20), 0.004
    sim = LidarSphereScenes(radius_m=NOMINAL_M + truth)
    z = []
    for seed in seeds:
        system = SphereScansAudit(scans_of(sim, seed))
        candidate = next(c for c in system.candidates() if c.effect == "sphere_radius")
        estimate, std = system.estimate(system.fit((candidate,)), candidate)
        z.append((estimate["dR_m"] - truth) / std["dR_m"])
    n = len(z)
    assert chi2.ppf(0.0005, n) / n <= np.mean(np.square(z)) <= chi2.ppf(0.9995, n) / n, np.round(z, 2)


# --- the audit, blind -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1])
def test_sphere_radius_is_named_with_its_size(seed):
    found = the(audit(LidarSphereScenes(radius_m=NOMINAL_M + 0.005), seed), "sphere_radius")
    assert within_3_sigma(found["estimate"]["dR_m"], found["std"]["dR_m"], 0.005)
    assert found["gain"]["heldout_rms_after"] < found["gain"]["heldout_rms_before"]


@pytest.mark.parametrize("seed", [0, 1])
def test_range_offset_is_named_not_a_radius_or_a_range_term(seed):
    contract = audit(LidarSphereScenes(range_offset_m=0.03), seed)
    assert names(contract) == ["range_offset"]
    found = the(contract, "range_offset")
    assert within_3_sigma(found["estimate"]["b_m"], found["std"]["b_m"], 0.03)


def radius_held_by_a_range_term(sim: LidarSphereScenes, seed: int, x0: float) -> float:
    """The constant radius ``dR`` a model ``R + dR + slope (rho - x0)`` of each return's range ``rho`` holds when
    each scene's sphere is ``R + slope (d - d_mid)`` (d its centre's range): derived, not fitted by the audit.

    A return on a ray ``alpha`` off the line of sight meets the sphere at ``rho = d cos(alpha) - R cos(i)``
    (``sin(alpha) = R sin(i) / d``), so the model's radius changes across each scene's cap by ``-slope (d - rho)``
    where the truth's does not.  The centres take part of that: a shift ``delta`` along the line of sight moves a
    return's distance from the centre by ``delta n.u0 = delta (cos(i) cos(alpha) + (R / d) sin^2(i))``, and the
    constant the rest.  To first order in ``delta`` (about ``slope R``) the fit is linear: the misfit
    ``-slope (d - rho)`` is regressed, in range units (the residual is a range: divided by ``cos(i)``), on the
    constant, the slope's own column, and each scene's shift, over the returns the audit keeps (``i <= 80 deg``).
    ``dR = slope (x0 - d_mid) - constant``; the leading part of the constant is ``slope R^2 sin^2(i) / (2 d)``,
    which the first-order value ``slope (x0 - d_mid)`` leaves out (0.24 mm at these ranges)."""
    slope, centres = sim.radius_slope, sim.centres_m(seed)
    rows, misfit = [], []
    for s, (c, radius, points) in enumerate(zip(centres, sim.scene_radii_m(seed), sim.scenes(seed))):
        d = np.linalg.norm(c)
        u = points / np.linalg.norm(points, axis=1)[:, None]
        sin_i = np.clip(np.linalg.norm(np.cross(u, c), axis=1) / radius, 0.0, 1.0)
        kept = np.arcsin(sin_i) <= MAX_INCIDENCE_RAD
        sin_i, cos_alpha = sin_i[kept], u[kept] @ c / d
        cos_i = np.sqrt(1.0 - sin_i**2)
        rho = d * cos_alpha - radius * cos_i
        X = np.zeros((len(rho), 2 + len(centres)))
        X[:, 0], X[:, 1] = 1.0, rho - x0
        X[:, 2 + s] = cos_i * cos_alpha + radius / d * sin_i**2
        rows.append(X / cos_i[:, None])
        misfit.append(-slope * (d - rho) / cos_i)
    constant = np.linalg.lstsq(np.vstack(rows), np.concatenate(misfit), rcond=None)[0][0]
    return slope * (x0 - 0.5 * (min(sim.ranges_m) + max(sim.ranges_m))) - constant


@pytest.mark.parametrize("seed", [0, 1, 2011])  # 2011: an 89 mm range offset and a -13 mm radius had been named
def test_radius_changing_with_range_is_unlisted_in_range_not_a_range_offset(seed):
    """R(d) = R + slope (d - d_mid), not in the catalog.  Its look-alike, the range offset (also an apparent
    radius that changes with range), must not be named; the term's linear coefficient is the slope.

    A ``sphere_radius`` beside it is the radius at the term's x0 (the basis has no constant), which the model holds
    as :func:`radius_held_by_a_range_term` derives (the first-order ``slope (x0 - d_mid)`` is 0.29-0.31 mm off,
    1-3 reported sigma: measured on seeds 0-7).  It is compared within 3 reported sigma with the same model fitted
    to the same scenes without noise (the pseudo-true value, which holds the form the audit chose), and that value
    with the derivation within its neglected second order in the centre shift: ``delta^2 / (2 R)`` per return,
    ``delta = slope R``, in range units up to ``1 / cos(80 deg)`` times that (0.09 mm; measured 0.012-0.026 mm on seeds 0-7)."""
    slope, sim = -0.01, LidarSphereScenes(radius_slope=-0.01)
    result = run_audit(SphereScansAudit(scans_of(sim, seed)))
    contract = result.to_json()
    assert "range_offset" not in names(contract)
    term = [f for f in contract["findings"] if f["effect"] == "unlisted"]
    assert [f["driver"] for f in term] == ["range"], names(contract)
    assert term[0]["form"] in ("poly1", "poly2", "poly3")
    assert within_3_sigma(term[0]["estimate"]["coefficients"][0][0], term[0]["std"]["coefficients"][0][0], slope)
    if "sphere_radius" in names(contract):
        found = the(contract, "sphere_radius")
        exact = SphereScansAudit(scans_of(LidarSphereScenes(radius_slope=slope, range_noise_m=1e-6), seed))
        radius = next(c for c in result.final_effects if c.effect == "sphere_radius")
        pseudo_true = exact.estimate(exact.fit(result.final_effects), radius)[0]["dR_m"]
        assert within_3_sigma(found["estimate"]["dR_m"], found["std"]["dR_m"], pseudo_true)
        neglected = (slope * sim.radius_m) ** 2 / (2.0 * sim.radius_m * np.cos(MAX_INCIDENCE_RAD))
        derived = radius_held_by_a_range_term(sim, seed, term[0]["estimate"]["x0"])
        assert abs(pseudo_true - derived) < neglected, (pseudo_true, derived, neglected)


@pytest.mark.parametrize("seed", [0, 1, 2000])
def test_range_error_growing_with_incidence_is_unlisted_in_incidence(seed):
    """A range error ``a (i / 90 deg)^2``, a = 10 mm: a polynomial in incidence, not its look-alike the range
    offset.  On seed 2000 the score test ranked the offset first among the catalog's (F 414 against the radius's
    379) and it passed BIC and held-out on its own (-16 mm, 20 sigma): it is named only if it predicts held-out
    data at least as well as the best library term on the same residual, and a cubic in incidence does better."""
    contract = audit(LidarSphereScenes(incidence_error_m=0.01), seed)
    assert names(contract) == ["unlisted:incidence"]
    if seed == 2000:  # the offset is listed as rejected, with what outdid it
        offset = [r for r in contract["rejected"] if r["effect"] == "range_offset"]
        assert [(r["reason"], r["outdone_by"]["driver"]) for r in offset] == [("outdone", "incidence")], offset
    found = contract["findings"][0]
    # the curvature stays: stepped down at the library's level (1e-5 over its terms) the term was linear on all
    # three seeds, the quadratic then reported as structure that remains (p 2e-6, 4.7e-6, 8.6e-5)
    assert found["form"] in ("poly2", "poly3"), found["form"]
    assert found["gain"]["heldout_rms_after"] < found["gain"]["heldout_rms_before"]


@pytest.mark.parametrize("seed", range(4))
def test_null_names_nothing(seed):
    contract = audit(LidarSphereScenes(), seed)
    assert contract["findings"] == []


@pytest.mark.parametrize("seed", range(3))
def test_scene_scatter_is_not_a_range_effect(seed):
    """Every scene's ball 2 mm off on its own (an inflatable target): the scatter is the base model's tau, never a
    range offset or a term.  The scenes' own mean radius is a real offset of these data: named, it must agree
    with it (the realised mean of 8 draws, not the population's 0.3 m)."""
    sim = LidarSphereScenes(scene_radius_sigma_m=0.002)
    contract = audit(sim, seed)
    assert set(names(contract)) <= {"sphere_radius"}, names(contract)
    if contract["findings"]:
        found = the(contract, "sphere_radius")
        realised = float(np.mean(sim.scene_radii_m(seed))) - NOMINAL_M
        assert within_3_sigma(found["estimate"]["dR_m"], found["std"]["dR_m"], realised)


def test_fewer_than_three_scenes_are_refused():
    sim = LidarSphereScenes(ranges_m=(2.0, 3.0))
    with pytest.raises(gq.DegenerateScansError, match="at least 3"):
        scans_of(sim, 0)


# --- real scans -----------------------------------------------------------------------------------------------

@pytest.mark.skipif(not SHARED.is_dir(), reason="shared SphereCalib data not present")
def test_real_lidar_scans_import_and_audit(tmp_path, capsys):
    """The SphereCalib LiDAR scans through the importer and the CLI: every scene's ball found, files unchanged,
    the contract's blocks present (what the audit names is reported in docs/audit.md)."""
    rec, out = tmp_path / "rec", tmp_path / "audit.json"
    assert main(["import", "spherecalib-lidar", str(SHARED), str(rec)]) in (0, None)
    copied = sorted((rec / "lidar0").glob("*.xyz.gz"))
    assert [f.read_bytes() for f in copied] == [f.read_bytes() for f in
                                                sorted(SHARED.glob("L1_S*.xyz.gz"), key=lambda f: int(f.name[4:-7]))]
    assert main(["audit", str(rec), "--system", "qc", "--json", str(out)]) in (0, None)
    contract = json.loads(out.read_text())
    assert contract["system"] == "qc" and contract["base_model"] == "sphere"
    assert set(contract["remaining"]) == {"lidar0/sphere"}
    assert not any("left out" in n for n in contract.get("notes", []))


def test_shipped_recording_is_the_upstream_scans_and_audits(tmp_path):
    """data/spherecalib_lidar (in every clone): the upstream files byte for byte (sha256 in SOURCE.md), audited."""
    first = (SHIPPED / "lidar0" / "1000000000.xyz.gz").read_bytes()
    assert hashlib.sha256(gzip.decompress(first)).hexdigest() == \
        "263ce8357b9f0360d208527a23ba557fb0b14d5d2d389c07007bd93d99fac06a"  # L1_S1.xyz, SOURCE.md
    out = tmp_path / "audit.json"
    assert main(["audit", str(SHIPPED), "--system", "qc", "--json", str(out)]) in (0, None)
    contract = json.loads(out.read_text())
    assert contract["system"] == "qc" and "lidar0/sphere" in contract["remaining"]


@pytest.mark.parametrize("radius", ["abc", -0.3, 0])
def test_a_nominal_radius_that_is_no_radius_is_refused_in_one_line(tmp_path, capsys, radius):
    import shutil
    import yaml
    rec = tmp_path / "rec"
    shutil.copytree(SHIPPED, rec)
    meta_file = rec / "lidar0" / "sensor.yaml"
    meta = yaml.safe_load(meta_file.read_text())
    meta["sphere_radius_m"] = radius
    meta_file.write_text(yaml.safe_dump(meta))
    assert main(["audit", str(rec), "--system", "qc", "--json", str(tmp_path / "a.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sphere_radius_m" in err[0] and not (tmp_path / "a.json").exists(), err
