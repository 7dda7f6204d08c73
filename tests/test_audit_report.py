"""The audit report: one self-contained, well-formed HTML file that names every finding and shows its evidence."""
import base64
import dataclasses
import re
from html.parser import HTMLParser

import numpy as np
import pytest
from matplotlib.figure import Figure

from selfcal.audit.engine import run_audit
from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
from selfcal.audit.report import format_estimate, num, pval, render_report, write_report
from selfcal.core.inertial import ImuNoise
from selfcal.sim.imu import ImuScenario, TemperatureProfile, random_intrinsics
from selfcal.sim.trajectories import MultiPositionTrajectory

PNG_URI = '<img src="data:image/png;base64,'
VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}


def small_audit(seed, **intrinsics):
    """The IMU audit on a short simulated multi-position recording (about 1 s)."""
    scenario_kw = intrinsics.pop("scenario", {})
    rec = ImuScenario(MultiPositionTrajectory(n_poses=16, seed=seed), *random_intrinsics(seed, **intrinsics),
                      ImuNoise(accelerometer_random_walk=0, gyroscope_random_walk=0), rate_hz=100,
                      **scenario_kw).perturbed_measurements(seed)
    data = rec.imu("imu0")
    return run_audit(ImuIntrinsicsAudit(data, float(data.meta.get("gravity_m_s2", 9.80665)), base="standard"))


@pytest.fixture(scope="module")
def result():
    r = small_audit(1, g_sensitivity=2e-4)
    assert r.findings, "the scenario holds an effect outside the standard model (g-sensitivity)"
    return r


@pytest.fixture(scope="module")
def page(result):
    return render_report(result)


@pytest.fixture(scope="module")
def temperature_result():
    """Gyro bias linear in a temperature that rises almost linearly in time: a channel-coordinate finding."""
    return small_audit(2, g_sensitivity=2e-4, gyro_temperature_slope=2e-3,
                       scenario={"temperature": TemperatureProfile(20.0, 30.0, 1000.0)})


class StrictParser(HTMLParser):
    """Parses the page and records every structural error: unclosed, unexpected or mismatched tags."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack, self.errors, self.images, self.text = [], [], [], []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.images.append(dict(attrs))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        if tag == "img":
            self.images.append(dict(attrs))

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes <{self.stack[-1] if self.stack else None}>")
            if tag in self.stack:
                del self.stack[len(self.stack) - 1 - self.stack[::-1].index(tag):]
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def parse(page: str) -> StrictParser:
    parser = StrictParser()
    parser.feed(page)
    parser.close()
    assert not parser.errors, parser.errors[:5]
    assert not parser.stack, f"unclosed tags: {parser.stack}"
    return parser


def assert_self_contained(parser: StrictParser, page: str):
    assert "<script" not in page and "<link" not in page and "@import" not in page
    for img in parser.images:
        src = img["src"]
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1]).startswith(b"\x89PNG\r\n\x1a\n")
    assert not re.search(r"""(src|href)=["']?(https?:|//|file:)""", page)


# --- the file -----------------------------------------------------------------------------------------------------

def test_report_is_one_self_contained_well_formed_file(result, tmp_path):
    path = write_report(result, tmp_path / "audit.html", {"recording": "sim/seed1"})
    assert path == tmp_path / "audit.html" and path.is_file()
    assert list(tmp_path.iterdir()) == [path]  # written atomically: no temporary left behind
    page = path.read_text(encoding="utf-8")
    parser = parse(page)
    assert_self_contained(parser, page)
    text = " ".join(parser.text)
    assert "sim/seed1" in text and "standard" in text
    assert "Residual diagnostics" in text and "Search history" in text


def test_every_finding_named_with_its_figure(result, page):
    parser = parse(page)
    text = " ".join(parser.text)
    for i, finding in enumerate(result.findings, 1):
        assert finding["effect"] in text
        assert f"{i}. {finding['effect']} on {finding['target']}" in text
    before_after = [img for img in parser.images if "residuals before and after" in img.get("alt", "")]
    assert len(before_after) == len(result.findings)
    assert page.count(PNG_URI) >= len(result.findings)


def test_summary_states_base_and_final_rms(result, page):
    summary = page.split('<div class="summary">', 1)[1].split("</div>", 1)[0]
    for finding in result.findings:
        base = next(f for f in result.base_fit.families if f.label == finding["target"])
        final = next(f for f in result.final_fit.families if f.label == finding["target"])
        assert f"leaves {num(base.rms, 3)}" in summary and f"brings it to {num(final.rms, 3)}" in summary
        assert finding["effect"] in summary and finding["target"] in summary


def test_ambiguity_warning_is_shown(result, page):
    findings = [dict(f) for f in result.findings]
    findings[0]["ambiguous_with"] = [{"effect": "bias_drift", "target": findings[0]["target"],
                                      "delta_bic_vs_accepted": 1.7}]
    warned = render_report(dataclasses.replace(result, findings=findings))
    text = " ".join(parse(warned).text)
    assert "Ambiguous" in text and "cannot be told apart from" in text and "bias_drift" in text
    assert 'class="amb"' in warned and 'class="ambbox"' in warned
    assert "cannot be told apart" not in page and 'class="ambbox"' not in page


def test_channel_coordinate_finding_and_real_ambiguity(temperature_result):
    page = render_report(temperature_result)
    parser = parse(page)
    assert_self_contained(parser, page)
    text = " ".join(parser.text)
    for finding in temperature_result.findings:
        assert finding["effect"] in text
        if finding.get("ambiguous_with"):
            assert "cannot be told apart from" in text
            for rival in finding["ambiguous_with"]:
                assert rival["effect"] in text
    assert page.count(PNG_URI) >= len(temperature_result.findings)


def test_no_finding_is_reported_as_a_valid_answer(result):
    empty = dataclasses.replace(result, findings=[], fits=[result.base_fit], final_fit=result.base_fit,
                                final_effects=result.base_fit.effects, history=result.history[:1])
    empty.history = [dict(empty.history[0], accepted=None)]
    parser = parse(render_report(empty))
    text = " ".join(parser.text)
    assert "no evidence against" in text


def test_extras_noise_and_simulation(result, tmp_path):
    fig = Figure(figsize=(3, 2))
    fig.subplots().loglog([1, 10, 100], [1e-3, 4e-4, 5e-4])
    png = tmp_path / "allan.png"
    fig.savefig(png, format="png")
    extras = {"noise": [{"title": "gyro Allan deviation", "figure": fig,
                         "table": [{"axis": "x", "best_extension": "gauss_markov", "delta_bic": -42.0}]},
                        {"title": "accel Allan deviation", "png_path": str(png), "table": [{"axis": "x"}]}],
              "simulation": [{"family": "imu0/gyro", "unit": "rad s^-1", "measured_base": 2.1e-3,
                              "simulated_base": 1.0e-4, "measured_final": 9.0e-5, "simulated_final": 8.7e-5}]}
    page = write_report(result, tmp_path / "r.html", extras).read_text()
    parser = parse(page)
    assert_self_contained(parser, page)
    text = " ".join(parser.text)
    assert "gyro Allan deviation" in text and "accel Allan deviation" in text and "gauss_markov" in text
    assert "Measured against simulated" in text
    assert "the base model's simulation predicts" in text and "extended model's simulation predicts" in text
    for column in ("measured base", "simulated base", "measured final", "simulated final"):
        assert column in text
    assert page.count(PNG_URI) >= len(result.findings) + 2


# --- formatting ---------------------------------------------------------------------------------------------------

def test_number_formatting():
    assert num(0.0011) == "0.0011"
    assert num(0.038898600535, 3) == "0.0389"
    assert num(2.77e-4, 3) == "2.77&times;10<sup>&minus;4</sup>"
    assert num(-500.0592) == "&minus;500.1"
    assert num(None) == "&ndash;" and num(float("nan")) == "nan"
    assert pval(3.127e-81) == "3.1&times;10<sup>&minus;81</sup>" and pval(0.0123) == "0.012"
    assert "300" in pval(0.0)


def test_estimate_formatting_with_units():
    scale = format_estimate("accel_scale", {"scale": [-0.0012739, -0.0023524, -0.000948]},
                            {"scale": [2.0e-5, 8.3e-6, 8.8e-6]})
    assert "ppm" in scale and "&minus;1274&nbsp;&plusmn;&nbsp;20" in scale
    angles = format_estimate("accel_misalignment", {"angles": [0.0042563, -0.0102344, 0.0218477]},
                             {"angles": [3.0e-5, 1.2e-4, 2.7e-5]})
    assert "mrad" in angles and "4.256&nbsp;&plusmn;&nbsp;0.030" in angles and ">yz<" in angles
    matrix = format_estimate("gyro_g_sensitivity", {"matrix": list(np.arange(1, 10) * 1e-5)},
                             {"matrix": [1e-6] * 9})
    assert matrix.count('class="erow"') == 3 and "rad s<sup>&minus;1</sup> per m s<sup>&minus;2</sup>" in matrix
    slope = format_estimate("bias_temperature", {"slope": [1e-3, -2e-3, 5e-4], "unit": "rad s^-1 per degC",
                                                 "target": "imu0/gyro"}, {"slope": [1e-4] * 3})
    assert "per degC" in slope and "imu0/gyro" not in slope


# --- what the report says next to its numbers: axes, units, what the plots show -------------------------------

def test_wide_tables_scroll_instead_of_overflowing_the_page(page):
    assert '<div class="wide"><table><tr><th rowspan="2">family</th>' in page  # the residual diagnostics
    assert ".wide{overflow-x:auto" in page


def test_measured_vs_simulated_sentences_name_the_axis(result):
    rows = [{"family": "imu0/gyro", "axis": axis, "unit": "rad s^-1", "measured_base_fit": 2e-3,
             "simulated_base_model_base_fit": 1e-3, "simulated_final_model_base_fit": 2e-3,
             "measured_final_fit": 1e-3, "simulated_final_model_final_fit": 1e-3} for axis in "xyz"]
    text = " ".join("".join(parse(render_report(result, {"simulation": rows})).text).split())
    for axis in "xyz":
        assert f"imu0/gyro {axis}: the base model's simulation predicts a residual of" in text


def test_finding_plot_titles_say_what_the_x_axis_shows():
    from selfcal.audit.report.figures import plotted_against
    assert plotted_against("angular rate", ["angular_rate"]) == "angular rate"
    assert plotted_against("orientation", ["up_x", "up_y", "up_z"]) == "orientation"
    # a residual without the effect's coordinate is plotted against time, and the title says so
    assert plotted_against("angular rate", ["time_s"]) == "time (angular rate is not a coordinate of this residual)"


def test_allan_plots_and_table_name_axes_and_print_noise_density_and_random_walk_with_units(result, tmp_path):
    from selfcal.audit.noise import noise_audit
    from selfcal.audit.report import allan_table, plot_allan
    rate_hz, density = 100.0, 2e-3  # white gyro noise, rad/s/sqrt(Hz): per-sample sigma = N sqrt(rate)
    samples = np.random.default_rng(3).normal(0.0, density * np.sqrt(rate_hz), (10_000, 3))
    noise = noise_audit(samples, rate_hz, "gyro")
    table = allan_table(noise)
    assert [row["axis"] for row in table] == ["x", "y", "z"]
    # N read off 100 s of white noise: the short-tau Allan points have thousands of degrees of freedom (a few
    # percent at most); 10 % would catch a variance printed for a deviation or a missing sqrt(rate)
    for row in table:
        assert abs(row["N [rad/s/sqrt(Hz)]"] / density - 1) < 0.10
        assert row["K [rad/s^2/sqrt(Hz)]"] >= 0
    png = plot_allan(noise, tmp_path / "allan.png")
    page = render_report(result, {"noise": [{"title": "Allan deviation of imu0/gyro", "png_path": str(png),
                                             "table": table}]})
    assert "<th>N [rad/s/sqrt(Hz)]</th><th>K [rad/s^2/sqrt(Hz)]</th>" in page
    assert "axis 0" not in page
    from selfcal.audit.report.figures import noise_figures
    legend = noise_figures("accel", noise.axes[0])  # the plot's legend text, with the accelerometer's units
    assert re.fullmatch(r"N = \S+ m/s\^2/sqrt\(Hz\)\nK = \S+ m/s\^3/sqrt\(Hz\)", legend)
