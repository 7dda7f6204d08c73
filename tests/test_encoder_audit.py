"""The encoder audit on simulated recordings holding effects it is not told about (and a null case).

Tolerances from the reported covariance: a scalar estimate within 3 sigma of the truth (two-sided 99.7 %); the
per-diode gains as a whole by the sum of squared z-scores below the chi-square 99.9 % quantile with n dof.
"""
import json

import numpy as np
import pytest
from scipy.stats import chi2

from selfcal.audit import encoder as audit_encoder
from selfcal.audit.engine import run_audit
from selfcal.cli.main import main
from selfcal.pipelines import encoder as pe
from selfcal.sim.encoder import EncoderScenario

TINY = dict(l=5, n_diodes=64, n_positions=24, cells_per_image=12.0)


def audit(sc, seed=0):
    rec, _ = sc.perturbed_measurements(seed)
    system = pe.audit_system(rec, frames={"array0": sc.perturbed_frames(seed)})
    return system, run_audit(system).to_json()


def test_null_recording_gives_no_finding():
    system, out = audit(EncoderScenario(seed=11, **TINY))
    assert out["findings"] == []
    assert out["final_model"] == ["ml"]
    assert "information_fraction" in system.diagnostics["eccentricity"]


def test_audit_reports_its_stages_through_the_progress_callback():
    """What a long run is doing: base fit, its cross-validation, each search step, the final residual tests."""
    sc = EncoderScenario(seed=11, **TINY)
    rec, _ = sc.perturbed_measurements(0)
    system = pe.audit_system(rec, frames={"array0": sc.perturbed_frames(0)})
    messages = []
    run_audit(system, progress=messages.append)
    assert messages[0].startswith("fitting the base model") and messages[1].startswith("cross-validating")
    steps = [m for m in messages if m.startswith("step")]  # each step is announced by its scoring, then named
    assert steps[0].startswith("step 1 (catalog)") and any(m.startswith("catalog: score") for m in messages)
    assert any(m.startswith("step") and "(library)" in m for m in messages)
    assert messages[-1].startswith("testing what remains")


def test_recording_above_the_row_budget_is_audited_on_every_kth_position(monkeypatch):
    """The default simulation (240 positions x 1024 diodes) is above the budget: the base fit, the calibration
    estimate and the eccentricity check must all run on the same subset (they crashed on a missing position)."""
    monkeypatch.setattr(audit_encoder, "MAX_ROWS", 24 * 64 // 2)
    system, out = audit(EncoderScenario(seed=11, **TINY))
    assert np.array_equal(system.positions, system.problem.used_positions()[::2])
    assert out["findings"] == []
    assert "information_fraction" in system.diagnostics["eccentricity"]


@pytest.mark.slow   # ~30 s: 64 gain columns in every fit and fold
def test_hidden_prnu_is_named_with_its_size():
    sc = EncoderScenario(seed=12, prnu_sigma=0.01, **TINY)
    _, out = audit(sc)
    assert [f["effect"] for f in out["findings"]] == ["prnu"]
    f = out["findings"][0]
    gain, sigma = np.array(f["estimate"]["gain"]), np.array(f["std"]["gain"])
    z2 = float(np.sum(((gain - sc.gain[0]) / sigma) ** 2))
    assert z2 < chi2.ppf(0.999, gain.size)
    true_rms = float(np.sqrt(np.mean(sc.gain[0] ** 2)))
    assert abs(f["estimate"]["rms"] - true_rms) < 3 * f["std"]["rms"] + 1e-12
    assert f["gain"]["heldout_rms_after"] < f["gain"]["heldout_rms_before"]


def test_hidden_temperature_scale_is_named_with_its_size(tmp_path):
    sc = EncoderScenario(seed=13, temperature_scale_per_degC=5e-5, temperature_range_degC=10.0, **TINY)
    sc.write(tmp_path / "rec", seed=0)
    assert main(["audit", str(tmp_path / "rec"), "--system", "encoder", "--json", str(tmp_path / "a.json")]) == 0
    out = json.loads((tmp_path / "a.json").read_text())
    assert [f["effect"] for f in out["findings"]] == ["temperature_scale"]
    f = out["findings"][0]
    assert abs(f["estimate"]["k_per_degC"] - 5e-5) < 3 * f["std"]["k_per_degC"]
    assert "eccentricity" in out["diagnostics"]


@pytest.mark.parametrize("seed", [14, 15, 3003])  # 3003: LM accepted no step and returned its start (now retried
# with diagonal damping; benchmarks/audit_catalog_recall.py)
def test_compressive_diode_response_is_unlisted_quadratic_in_signal(seed):
    """A diode chain that compresses: ``s - c s^2 / adc_max`` with c = 5 % loss at full scale; no catalog entry.
    The audit must name it by the driver ``signal`` (the predicted counts) with the quadratic coefficient
    ``-c / adc_max`` (first order in c; the linear part is the illumination's, left free).  Not eccentricity,
    PRNU or a temperature scale."""
    c = 0.05
    sc = EncoderScenario(seed=seed, response_compression=c, **TINY)
    _, out = audit(sc)
    assert [(f["effect"], f.get("driver")) for f in out["findings"]] == [("unlisted", "signal")], out["findings"]
    f = out["findings"][0]
    assert f["form"] in ("poly2", "poly3")  # 3003: the quadratic alone fails the held-out margin, the cubic passes
    quadratic, sigma = f["estimate"]["coefficients"][1][0], f["std"]["coefficients"][1][0]
    assert abs(quadratic - (-c / sc.adc_max)) < 3 * sigma, (quadratic, sigma, -c / sc.adc_max)
    assert f["gain"]["heldout_rms_after"] < f["gain"]["heldout_rms_before"]


def shuffled_positions(n: int, seed: int) -> np.ndarray:
    """A revolution's positions visited in random order: the disk angle is then not collinear with the frame index,
    along which the temperature ramps (in order, a temperature term and a position term would be one)."""
    rng = np.random.default_rng([seed, 5])
    return (rng.permutation(n) + rng.uniform(-0.25, 0.25, n)) * 2 * np.pi / n


# 0.5 counts per degC: a 12-bit array's dark level (dark current and ADC offset) drifting by 4 counts over the 8.5 K
# the TINY run spans.  Measured sigma of the slope: 0.039 counts/degC (seeds 16, 17: 13 sigma from zero).
A0_PER_DEGC = 0.5


@pytest.mark.parametrize("seed", [16, 17])
def test_dark_level_drifting_with_temperature_is_unlisted_linear_in_temperature_not_a_temperature_scale(seed):
    """The dark level rises with temperature: ``a0 + k (T - 25)``, k = 0.5 counts/degC; no catalog entry.  A
    look-alike of ``temperature_scale`` (same driver, an image scale ``p`` instead of an offset): it must not be
    named, nor PRNU or eccentricity.  The library's offset linear in ``temperature`` is exactly the drift (its
    constant goes to the base's ``a0``), so its slope is within 3 reported sigma of k."""
    positions = shuffled_positions(TINY["n_positions"], seed)
    sc = EncoderScenario(seed=seed, a0_per_degC=A0_PER_DEGC, temperature_range_degC=10.0, positions_rad=positions,
                         **TINY)
    _, out = audit(sc)
    assert [(f["effect"], f.get("driver")) for f in out["findings"]] == [("unlisted", "temperature")], \
        out["findings"]
    f = out["findings"][0]
    assert f["form"] in ("poly1", "poly2", "poly3"), f["form"]
    # coefficients of (T - x0)^j: the slope is k, any higher power of a straight line is zero
    truth = [A0_PER_DEGC] + [0.0] * (len(f["estimate"]["coefficients"]) - 1)
    for j, (c, sigma) in enumerate(zip(f["estimate"]["coefficients"], f["std"]["coefficients"])):
        assert abs(c[0] - truth[j]) < 3 * sigma[0], (f["form"], j + 1, c[0], sigma[0], truth[j])
    assert f["gain"]["rms_after"] < f["gain"]["rms_before"]
    assert f["gain"]["heldout_rms_after"] < f["gain"]["heldout_rms_before"]
