"""The audit report: one self-contained HTML file that shows what the model got wrong and why each finding holds.

An engineer reads, top to bottom:

1. the header (system, recording, base and final model, date) and a plain-language summary;
2. the findings table in acceptance order: estimate with 1-sigma, evidence, gain, and, prominently, the
   effects the data cannot tell apart from an accepted one;
3. per finding, the target residuals against the coordinate the effect's signature depends on, before and
   after the effect was added, on the same y scale (the gain is what disappears between the two rows);
4. diagnostics of the final residuals (:mod:`selfcal.audit.diagnostics`): bias, serial correlation,
   normality, dependence on any coordinate;
5. the search history: every candidate's evidence at every step against the Bonferroni threshold;
6. optional sections from ``extras``: Allan-deviation noise audits, measured against simulated residuals.

Plots are matplotlib figures rendered with the Agg canvas (no pyplot, no global state) and embedded as
base64 PNG; the CSS is a few inline rules; there is no JavaScript.  The file is written atomically.
"""
from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import math
import re
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from selfcal.audit.diagnostics import component_names, diagnose
from selfcal.audit.engine import FAMILY_ALPHA, AuditResult, Candidate, Fit, ResidualFamily
from selfcal.io.atomic import atomic_write_text

# estimate keys shown in a unit engineers read off datasheets: key -> (unit shown, factor from the JSON unit)
DISPLAY_UNITS = {"scale": ("ppm", 1e6), "angles": ("mrad", 1e3), "dt_s": ("ms", 1e3), "r_m": ("mm", 1e3),
                 "tau_s": ("s", 1.0)}
AXES3 = ("x", "y", "z")
ACCEL_ANGLES = ("yz", "zy", "zx")  # Tedaldi's upper-triangular non-orthogonality angles
OFF_DIAGONAL = ("xy", "xz", "yx", "yz", "zx", "zy")  # full-matrix off-diagonal entries, row-major
P_STRONG, P_WEAK = 1e-3, 1e-2  # shading levels of p-values in the diagnostics table

CSS = """
body{font:15px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;color:#222;max-width:1180px;
margin:0 auto;padding:18px 28px 60px}
h1{font-size:24px;margin:0 0 6px}h2{font-size:19px;margin:34px 0 8px;border-bottom:1px solid #ccc;padding-bottom:3px}
h3{font-size:16px;margin:22px 0 6px}
table{border-collapse:collapse;font-size:13px;margin:8px 0 4px}
th,td{border:1px solid #d4d4d4;padding:4px 7px;vertical-align:top;text-align:left}
th{background:#f1f1f1;font-weight:600}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
.meta td{border:none;padding:1px 12px 1px 0}.meta td:first-child{color:#666}
.summary{background:#f6f8fa;border-left:4px solid #4a7ab5;padding:10px 14px;margin:12px 0}
.amb{background:#fff1d6;border:2px solid #e08a00;color:#5a3600}
.ambbox{background:#fff1d6;border:2px solid #e08a00;border-radius:4px;padding:8px 12px;margin:10px 0;color:#5a3600}
.el{display:inline-block;margin-right:10px;white-space:nowrap}.el i{color:#777;font-style:normal;margin-right:3px}
.small{font-size:12px;color:#555}.mean{color:#555}
.pbad{background:#f6c9c4}.pwarn{background:#fbe7c0}
.acc{background:#cdebd0;font-weight:600}.sig{background:#fbe7c0}.inmodel{color:#999;background:#f5f5f5}
img{max-width:100%;height:auto;border:1px solid #e4e4e4;margin:6px 0}
.erow{white-space:nowrap}td.ev{min-width:10em}td.hist{white-space:nowrap}
td.gain{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:8px 0 18px}figcaption{font-size:13px;color:#444}
"""


# --- public API ---------------------------------------------------------------------------------------------------

def write_report(result: AuditResult, path, extras: dict | None = None) -> Path:
    """Write the audit report as one self-contained HTML file (atomically).

    Parameters
    ----------
    result : AuditResult
        The audit (findings, fits before/after each finding, search history).
    path : str or Path
        Output file; its folder must exist.
    extras : dict, optional
        ``recording`` (path shown in the header), ``run_date`` (text; default: now),
        ``noise``: list of ``{"title", "png_path" or "figure" (matplotlib Figure), "table" (list of dicts),
        "text"}`` (Allan-deviation noise audits), ``simulation``: list of dicts (one row per residual family,
        e.g. ``family, measured_base, simulated_base, measured_final, simulated_final``; every column is shown).

    Returns
    -------
    Path
        ``path``.
    """
    return atomic_write_text(Path(path), render_report(result, extras))


def render_report(result: AuditResult, extras: dict | None = None) -> str:
    """The report's HTML text (see :func:`write_report`)."""
    extras = dict(extras or {})
    parts = [_header(result, extras), _summary(result, extras.get("noise_findings", [])), _findings_table(result),
             _finding_sections(result),
             _diagnostics_section(result.final_fit), _history_section(result)]
    if extras.get("noise"):
        parts.append(_noise_section(extras["noise"]))
    if extras.get("simulation"):
        parts.append(_simulation_section(extras["simulation"]))
    title = html.escape(f"selfcal audit: {result.system}" + (f" - {extras['recording']}" if extras.get("recording")
                                                             else ""))
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
            f"<title>{title}</title>\n<style>{CSS}</style>\n</head>\n<body>\n"
            + "\n".join(p for p in parts if p) + "\n</body>\n</html>\n")


def figure_to_data_uri(fig: Figure, dpi: int = 96) -> str:
    """``data:image/png;base64,...`` of a matplotlib figure (rendered by the Agg canvas)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return png_to_data_uri(buf.getvalue())


def png_to_data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


# --- number and unit formatting ----------------------------------------------------------------------------------

def _finite(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and math.isfinite(float(x))


def num(x, digits: int = 4) -> str:
    """A number in HTML with ``digits`` significant digits; scientific as ``1.23×10<sup>-5</sup>``."""
    if x is None:
        return "&ndash;"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if not isinstance(x, (int, float, np.integer, np.floating)):
        return html.escape(str(x))
    x = float(x)
    if not math.isfinite(x):
        return "nan" if math.isnan(x) else ("&infin;" if x > 0 else "&minus;&infin;")
    if x == 0.0:
        return "0"
    a = abs(x)
    if 1e-3 <= a < 10**digits:
        return _minus(f"{x:.{digits}g}")
    if 10**digits <= a < 1e6:
        return _minus(f"{x:.0f}")
    return _sci(x, digits)


def pval(p) -> str:
    """A p-value with 2 significant digits (below 1e-300 shown as a bound)."""
    if p is None or not _finite(p):
        return "&ndash;"
    p = float(p)
    if p < 1e-300:
        return "&lt; 10<sup>&minus;300</sup>"
    if p >= 1e-3:
        return f"{p:.2g}"
    return _sci(p, 2)


def _sci(x: float, digits: int) -> str:
    exponent = int(math.floor(math.log10(abs(x))))
    mantissa = x / 10.0**exponent
    if round(abs(mantissa), digits - 1) >= 10.0:
        mantissa, exponent = mantissa / 10.0, exponent + 1
    text = f"{mantissa:.{digits - 1}f}".rstrip("0").rstrip(".")
    return f"{_minus(text)}&times;10<sup>{_minus(str(exponent))}</sup>"


def _minus(s: str) -> str:
    return s.replace("-", "&minus;")


def unit_html(unit: str | None) -> str:
    """``m s^-2`` -> ``m s<sup>-2</sup>``."""
    if not unit:
        return ""
    return re.sub(r"\^(-?\d+)", lambda m: f"<sup>{_minus(m.group(1))}</sup>", html.escape(unit))


def unit_tex(unit: str | None) -> str:
    """``m s^-2`` -> ``m s$^{-2}$`` for matplotlib labels."""
    if not unit:
        return ""
    return re.sub(r"\^(-?\d+)", r"$^{\1}$", unit)


def _engineering_exponent(values) -> int:
    """Power of ten (multiple of 3) that brings the largest |value| into [1, 1000)."""
    finite = np.abs(np.asarray([v for v in np.ravel(values) if _finite(v)], dtype=float))
    finite = finite[finite > 0]
    if finite.size == 0:
        return 0
    e = int(math.floor(math.log10(finite.max())))
    return 3 * (e // 3)


def _value_sigma(v, s) -> str:
    """``value ± sigma``: sigma to 2 significant digits, the value to the same decimal place."""
    if not _finite(v):
        return num(v)
    if s is None or not _finite(s) or float(s) <= 0:
        return num(v)
    s = float(s)
    decimals = int(np.clip(1 - math.floor(math.log10(s)), 0, 8))
    return f"{_minus(f'{float(v):.{decimals}f}')}&nbsp;&plusmn;&nbsp;{s:.{decimals}f}"


def _element_labels(key: str, n: int, effect: str) -> list[str]:
    if n == 3 and key == "angles" and effect.startswith("accel"):
        return list(ACCEL_ANGLES)
    if n == 3:
        return list(AXES3)
    if n == 6 and key == "angles":
        return list(OFF_DIAGONAL)
    return [str(i) for i in range(n)]


def _estimate_unit(key: str, estimate: dict, effect: str) -> str | None:
    if key in DISPLAY_UNITS:
        return DISPLAY_UNITS[key][0]
    if key == "matrix" and effect == "gyro_g_sensitivity":
        return "rad s^-1 per m s^-2"
    if key == "bias":
        return "m s^-2" if effect.startswith("accel") else ("rad s^-1" if effect.startswith("gyro") else None)
    return estimate.get("unit") if isinstance(estimate.get("unit"), str) else None


def format_estimate(effect: str, estimate: dict, std: dict | None) -> str:
    """HTML of an estimate dict with its 1-sigma: vectors compactly, with units, matrices as 3 rows."""
    std = std or {}
    lines = []
    for key, value in estimate.items():
        if key in ("unit", "target"):  # the unit is shown with the numbers, the target has its own column
            continue
        if isinstance(value, str):
            lines.append(f"<div class=\"small\">{html.escape(key)}: {html.escape(value)}</div>")
            continue
        try:
            values = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
        except (TypeError, ValueError):  # not numbers: shown as they are
            lines.append(f"<div>{html.escape(key)}: {_cell(value)}</div>")
            continue
        try:
            sigmas = np.atleast_1d(np.asarray(std.get(key, np.nan), dtype=float)).ravel()
        except (TypeError, ValueError):
            sigmas = np.full(values.shape, np.nan)
        if sigmas.shape != values.shape:
            sigmas = np.full(values.shape, np.nan)
        factor = DISPLAY_UNITS[key][1] if key in DISPLAY_UNITS else 1.0
        values, sigmas = values * factor, sigmas * factor
        largest = np.nanmax(np.abs(values)) if np.any(np.isfinite(values)) else 0.0
        exponent = _engineering_exponent(values)
        if 1e-2 <= largest < 1e4 or (-3 <= exponent <= 3 and key in DISPLAY_UNITS):
            exponent = 0  # readable as it is
        if exponent:
            values, sigmas = values / 10.0**exponent, sigmas / 10.0**exponent
        unit = _estimate_unit(key, estimate, effect)
        bracket = " ".join(t for t in (f"&times;10<sup>{_minus(str(exponent))}</sup>" if exponent else "",
                                       unit_html(unit)) if t) or "&ndash;"
        head = f"<b>{html.escape(key)}</b> <span class=\"small\">[{bracket}]</span>"
        cells = [_value_sigma(v, s) for v, s in zip(values, sigmas)]
        if values.size == 1:
            body = cells[0]
        elif values.size == 9:
            body = "".join("<div class=\"erow\">" + " ".join(f"<span class=\"el\">{c}</span>"
                                                            for c in cells[3 * r:3 * r + 3]) + "</div>"
                           for r in range(3))
        else:
            labels = _element_labels(key, values.size, effect)
            items = [f"<span class=\"el\"><i>{html.escape(lab)}</i>{c}</span>" for lab, c in zip(labels, cells)]
            body = "".join(f"<div class=\"erow\">{' '.join(items[i:i + 3])}</div>" for i in range(0, len(items), 3))
        if values.size == 1:
            body = f"<div class=\"erow\">{body}</div>"
        lines.append(f"<div>{head}{body}</div>")
    return "".join(lines) if lines else "&ndash;"


# --- model names --------------------------------------------------------------------------------------------------

def _base_description(result: AuditResult) -> str:
    base = result.base_fit.effects
    if not base:
        return f"{result.base_model}-only" if result.base_model == "bias" else result.base_model
    return f"{result.base_model} ({', '.join(c.effect for c in base)})"


def _accepted_candidates(result: AuditResult) -> list[Candidate | None]:
    """The candidate accepted at each finding: the effect fits[i+1] has that fits[i] has not."""
    out = []
    for i, finding in enumerate(result.findings):
        cand = None
        if i + 1 < len(result.fits):
            new = [c for c in result.fits[i + 1].effects if c not in result.fits[i].effects]
            cand = new[-1] if new else None
        if cand is None:  # fall back on the final effects by name and target
            label = finding.get("target", "")
            cand = next((c for c in result.final_effects if c.effect == finding.get("effect")
                         and f"{c.sensor}/{c.target}" == label), None)
        out.append(cand)
    return out


def _family_by_label(fit: Fit, label: str) -> ResidualFamily | None:
    return next((f for f in fit.families if f.label == label), None)


# --- sections -----------------------------------------------------------------------------------------------------

def _family_alpha(result: AuditResult) -> float:
    """The level the search ran at: the first step's threshold times its number of open candidates."""
    if result.history and result.history[0].get("trials"):
        return float(result.history[0]["threshold"]) * len(result.history[0]["trials"])
    return FAMILY_ALPHA


def _header(result: AuditResult, extras: dict) -> str:
    final = result.to_json()["final_model"]
    date = extras.get("run_date") or _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    rows = [("system", html.escape(result.system))]
    if extras.get("recording"):
        rows.append(("recording", f"<code>{html.escape(str(extras['recording']))}</code>"))
    rows += [("base model", html.escape(_base_description(result))),
             ("final model", html.escape(" + ".join(final))),
             ("findings", str(len(result.findings))),
             ("search", f"{len(result.history)} step{'s' if len(result.history) != 1 else ''}, family-wise "
                        f"&alpha; = {num(_family_alpha(result))} per step (Bonferroni over the open candidates)"),
             ("run date", html.escape(str(date)))]
    table = "".join(f"<tr><td>{k}</td><td>{v}</td></tr>" for k, v in rows)
    return f"<h1>Audit report: {html.escape(result.system)}</h1>\n<table class=\"meta\">{table}</table>"


def _summary(result: AuditResult, noise_findings=()) -> str:
    """One paragraph: per residual family, what the base model leaves and what the accepted effects remove;
    then the noise-model findings of the Allan analysis, if any."""
    base_desc = _base_description(result)
    by_target: dict[str, list[int]] = {}
    for i, finding in enumerate(result.findings):
        by_target.setdefault(finding.get("target", "?"), []).append(i)
    sentences = []
    for label, idx in by_target.items():
        base_fam = _family_by_label(result.base_fit, label)
        final_fam = _family_by_label(result.final_fit, label)
        unit = unit_html(base_fam.unit) if base_fam else ""
        effects = ", ".join(f"<b>{html.escape(result.findings[i]['effect'])}</b>" for i in idx)
        last_gain = result.findings[idx[-1]].get("gain", {})
        before = num(base_fam.rms, 3) if base_fam else num(result.findings[idx[0]]["gain"].get("rms_before"), 3)
        after = num(final_fam.rms, 3) if final_fam else num(last_gain.get("rms_after"), 3)
        heldout = last_gain.get("heldout_rms_after")
        held_txt = f" (held-out {num(heldout, 3)})" if heldout is not None else ""
        leaves = (f"In {html.escape(label)} it leaves {before} {unit} RMS" if sentences else
                  f"The {html.escape(base_desc)} model leaves {before} {unit} RMS in {html.escape(label)}")
        sentences.append(f"{leaves}; accepting {effects} brings it to {after}{held_txt}.")
    untouched = [f for f in result.final_fit.families if f.label not in by_target]
    if result.findings and untouched:
        items = []
        for fam in untouched:
            base_fam = _family_by_label(result.base_fit, fam.label)
            before = num(base_fam.rms, 3) + " &rarr; " if base_fam else ""
            items.append(f"{html.escape(fam.label)} {before}{num(fam.rms, 3)} {unit_html(fam.unit)}")
        sentences.append("No effect was accepted on " + "; ".join(items) + " (changes come from shared parameters).")
    if not result.findings:
        rms = "; ".join(f"{html.escape(f.label)} {num(f.rms, 3)} {unit_html(f.unit)}"
                        for f in result.final_fit.families)
        sentences.append(f"No candidate effect is significant and predictive: the data give no evidence against the "
                         f"{html.escape(base_desc)} model (residual RMS: {rms}). That is a valid answer, not a "
                         "failure." if not noise_findings else
                         f"No deterministic effect is significant and predictive against the {html.escape(base_desc)} "
                         f"model (residual RMS: {rms}).")
    for finding in noise_findings:
        gain = finding.get("gain", {})
        sentences.append(f"The noise model is too optimistic: the Allan analysis names <b>{html.escape(finding['effect'])}"
                         f"</b> on {html.escape(finding.get('target', ''))} (white-noise-only prediction off by "
                         f"{num(100 * gain.get('rms_before', 0), 3)} % RMS over the tau range, extended model "
                         f"{num(100 * gain.get('rms_after', 0), 3)} %; see Noise).")
    out = f"<div class=\"summary\"><p>{' '.join(sentences)}</p></div>"
    return out + "".join(_ambiguity_box(f) for f in result.findings if f.get("ambiguous_with"))


def _ambiguity_text(finding: dict) -> str:
    rivals = finding.get("ambiguous_with") or []
    names = ", ".join(f"<b>{html.escape(str(r.get('effect')))}</b>"
                      + (f" on {html.escape(str(r['target']))}" if r.get("target") else "")
                      + (f" (&Delta;BIC {_signed(r['delta_bic_vs_accepted'])} vs accepted)"
                         if _finite(r.get("delta_bic_vs_accepted")) else "")
                      for r in rivals)
    return names


def _ambiguity_box(finding: dict) -> str:
    return (f"<div class=\"ambbox\">&#9888; <b>Ambiguous:</b> the data cannot tell "
            f"<b>{html.escape(finding['effect'])}</b> ({html.escape(finding.get('target', ''))}) apart from "
            f"{_ambiguity_text(finding)}. Both explain the residual about equally well (BIC within 6) and the rival "
            "loses its evidence once the accepted effect is in the model. Treat the cause as undetermined: only a "
            "recording in which the two causes vary independently can decide.</div>")


def _signed(x) -> str:
    x = float(x)
    return ("+" if x >= 0 else "") + num(x, 3)


def _findings_table(result: AuditResult) -> str:
    if not result.findings:
        return "<h2>Findings</h2><p>None: no candidate effect passed the significance, BIC and held-out tests.</p>"
    units = {f.label: f.unit for fit in result.fits for f in fit.families}
    rows = []
    for i, f in enumerate(result.findings, 1):
        ev, gain = f.get("evidence", {}), f.get("gain", {})
        unit = unit_html(units.get(f.get("target", ""), ""))
        evidence = (f"F = {num(ev.get('statistic'), 4)}<br>p = {pval(ev.get('p_value'))}"
                    f"<div class=\"small\">{html.escape(str(ev.get('diagnostic', '')))}</div>")
        gain_html = "".join(f"<div class=\"erow\">{line}</div>" for line in (
            f"RMS {num(gain.get('rms_before'), 3)} &rarr; {num(gain.get('rms_after'), 3)} {unit}",
            f"&Delta;BIC {num(gain.get('delta_bic'), 4)}",
            f"held-out {num(gain.get('heldout_rms_before'), 3)} &rarr; {num(gain.get('heldout_rms_after'), 3)}"))
        if f.get("ambiguous_with"):
            amb = f"<td class=\"amb\">&#9888; <b>cannot be told apart from</b> {_ambiguity_text(f)}</td>"
            effect = f"&#9888; <b>{html.escape(f['effect'])}</b>"
        else:
            amb, effect = "<td>&ndash;</td>", f"<b>{html.escape(f['effect'])}</b>"
        meaning = f"<br><span class=\"small\">{html.escape(f['meaning'])}</span>" if f.get("meaning") else ""
        sensor, target = str(f.get("sensor", "")), str(f.get("target", ""))
        quantity = target[len(sensor) + 1:] if target.startswith(f"{sensor}/") else target
        rows.append(f"<tr><td class=\"num\">{i}</td><td>{effect}{meaning}</td>"
                    f"<td title=\"{html.escape(target)}\">{html.escape(sensor)}<br>{html.escape(quantity)}</td>"
                    f"<td class=\"est\">{format_estimate(f['effect'], f.get('estimate', {}), f.get('std'))}</td>"
                    f"<td class=\"ev\">{evidence}</td><td class=\"gain\">{gain_html}</td>{amb}</tr>")
    head = ("<tr><th>#</th><th>effect</th><th>sensor<br>target</th><th>estimate &plusmn; 1&sigma;</th>"
            "<th>evidence</th><th>gain (before &rarr; after)</th><th>ambiguous with</th></tr>")
    return ("<h2>Findings, in the order accepted</h2>\n"
            "<p class=\"small\">Each finding was significant against the Bonferroni threshold of its step, lowered "
            "the BIC, and lowered the residual on data it was not fitted to (cross-validation over contiguous "
            "blocks in time). Held-out RMS is on the predicted block of each fold.</p>\n"
            f"<table>{head}{''.join(rows)}</table>")


# --- finding figures ----------------------------------------------------------------------------------------------

COORDINATE_SETS = {"orientation": ("up_x", "up_y", "up_z"), "rotation of each move": ("rot_x", "rot_y", "rot_z"),
                   "time": ("time_s",)}
COORDINATE_LABELS = {"up_x": "gravity direction x (sensor frame)", "up_y": "gravity direction y (sensor frame)",
                     "up_z": "gravity direction z (sensor frame)", "rot_x": "move rotation x [rad]",
                     "rot_y": "move rotation y [rad]", "rot_z": "move rotation z [rad]", "time_s": "time [s]"}
COMPONENT_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2")


def plot_coordinates(coordinate: str, family: ResidualFamily) -> list[str]:
    """The family coordinates a candidate's signature is plotted against (falls back on time)."""
    names = COORDINATE_SETS.get(coordinate, (coordinate,))
    present = [n for n in names if n in family.coordinates]
    if present:
        return present
    return ["time_s"] if "time_s" in family.coordinates else list(family.coordinates)[:1]


def _tex_num(x: float, digits: int = 3) -> str:
    """A number for a matplotlib label: ``1.23 \\times 10^{-5}`` in mathtext when it needs an exponent."""
    if not math.isfinite(x) or x == 0.0 or 1e-3 <= abs(x) < 1e4:
        return f"{x:.{digits}g}"
    exponent = int(math.floor(math.log10(abs(x))))
    mantissa = f"{x / 10.0**exponent:.{digits - 1}f}".rstrip("0").rstrip(".")
    return f"${mantissa}\\times10^{{{exponent}}}$"


def _scatter_components(ax, x, y, names):
    for j in range(y.shape[1]):
        ax.scatter(x, y[:, j], s=16, alpha=0.8, color=COMPONENT_COLOURS[j % len(COMPONENT_COLOURS)],
                   label=names[j] if j < len(names) else str(j), edgecolors="none")
    ax.axhline(0.0, color="#888", lw=0.8)
    ax.grid(True, alpha=0.3)


def _residual_scale(*families: ResidualFamily) -> tuple[int, float]:
    """Engineering exponent of the residuals and the half-range that holds all of them."""
    stacked = np.concatenate([np.ravel(f.physical) for f in families])
    stacked = stacked[np.isfinite(stacked)]
    if not stacked.size:
        return 0, 1.0
    exponent = _engineering_exponent(stacked)
    top = float(np.max(np.abs(stacked))) * 10.0**-exponent * 1.12
    return exponent, top or 1.0


def _residual_label(fam: ResidualFamily, exponent: int, title: str = "") -> str:
    scale = f"$10^{{{exponent}}}$ " if exponent else ""
    return f"{title}\nresidual [{scale}{unit_tex(fam.unit)}]" if title else f"residual [{scale}{unit_tex(fam.unit)}]"


def finding_figure(before: ResidualFamily, after: ResidualFamily, coordinate: str, effect: str) -> Figure:
    """Residuals of one family against the implicated coordinates: before (top row) and after (bottom row).

    One column per coordinate, one colour per residual component, one y scale for all panels, so the gain is
    what disappears from the top row to the bottom one.
    """
    coords = plot_coordinates(coordinate, before)
    n_cols = max(len(coords), 1)
    names = component_names(before)
    several = np.asarray(before.physical).reshape(len(before.physical), -1).shape[1] > 1
    fig = Figure(figsize=(max(3.5 * n_cols, 6.0) + (1.6 if several else 0.9), 5.4), layout="constrained")
    axes = fig.subplots(2, n_cols, sharey=True, squeeze=False)
    exponent, top = _residual_scale(before, after)
    factor = 10.0**-exponent
    for row, (fam, title) in enumerate(((before, "before"), (after, "after"))):
        phys = np.asarray(fam.physical, dtype=float).reshape(len(fam.physical), -1) * factor
        for col, cname in enumerate(coords):
            ax = axes[row, col]
            x = np.asarray(fam.coordinates.get(cname, np.full(len(phys), np.nan)), dtype=float)
            _scatter_components(ax, x, phys, names)
            if row == 1:
                ax.set_xlabel(COORDINATE_LABELS.get(cname, cname))
            if col == 0:
                ax.set_ylabel(_residual_label(fam, exponent, title))
            ax.text(0.02, 0.96, f"RMS {_tex_num(fam.rms)} {unit_tex(fam.unit)}", transform=ax.transAxes, va="top",
                    fontsize=9, bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.5})
    if several:
        fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside right upper", fontsize=9,
                   title="component", title_fontsize=9, markerscale=1.3)
    axes[0, 0].set_ylim(-top, top)
    fig.suptitle(f"{before.label} residual vs {coordinate}: before and after {effect}", fontsize=11)
    return fig


def rival_coordinate(effect: str, family: ResidualFamily) -> str | None:
    """The coordinate a rival effect's signature depends on, from its name (the JSON keeps only the name)."""
    if effect == "bias_drift":
        return "time"
    if effect.startswith("channel:"):
        return effect.split(":", 1)[1]
    if effect == "bias_temperature":
        return next((c for c in family.coordinates if c.lower().startswith("temp")), None)
    if effect in ("accel_scale", "accel_misalignment", "gyro_g_sensitivity"):
        return "orientation"
    if effect in ("gyro_scale", "gyro_misalignment"):
        return "rotation of each move"
    return None


def ambiguity_figure(before: ResidualFamily, coordinate: str, rival: str, rival_coord: str) -> Figure | None:
    """Why two causes cannot be told apart: the residual against both causes' coordinates, and (for two scalar
    coordinates) one coordinate against the other with their correlation coefficient.  None if the two
    coordinates are the same."""
    mine, theirs = plot_coordinates(coordinate, before), plot_coordinates(rival_coord, before)
    if mine == theirs:
        return None
    scalar = len(mine) == 1 and len(theirs) == 1
    panels = mine + theirs
    n_cols = len(panels) + (1 if scalar else 0)
    names = component_names(before)
    several = np.asarray(before.physical).reshape(len(before.physical), -1).shape[1] > 1
    fig = Figure(figsize=(max(3.3 * n_cols, 6.0) + (1.6 if several else 0.9), 3.1), layout="constrained")
    axes = fig.subplots(1, n_cols, squeeze=False)[0]
    exponent, top = _residual_scale(before)
    phys = np.asarray(before.physical, dtype=float).reshape(len(before.physical), -1) * 10.0**-exponent
    for ax, cname in zip(axes, panels):
        _scatter_components(ax, np.asarray(before.coordinates[cname], dtype=float), phys, names)
        ax.set_xlabel(COORDINATE_LABELS.get(cname, cname))
        ax.set_ylim(-top, top)
    axes[0].set_ylabel(_residual_label(before, exponent))
    for ax in axes[1:len(panels)]:
        ax.sharey(axes[0])
    if scalar:
        a = np.asarray(before.coordinates[mine[0]], dtype=float)
        b = np.asarray(before.coordinates[theirs[0]], dtype=float)
        ok = np.isfinite(a) & np.isfinite(b)
        r = float(np.corrcoef(a[ok], b[ok])[0, 1]) if ok.sum() > 2 and np.ptp(a[ok]) and np.ptp(b[ok]) else np.nan
        ax = axes[-1]
        ax.scatter(a, b, s=16, color="#555", edgecolors="none")
        ax.set_xlabel(COORDINATE_LABELS.get(mine[0], mine[0]))
        ax.set_ylabel(COORDINATE_LABELS.get(theirs[0], theirs[0]))
        ax.set_title(f"the two coordinates: r = {r:.4f}", fontsize=10)
        ax.grid(True, alpha=0.3)
    if several:
        fig.legend(*axes[0].get_legend_handles_labels(), loc="outside right upper", fontsize=9,
                   title="component", title_fontsize=9, markerscale=1.3)
    fig.suptitle(f"{before.label} residual before either effect, against {coordinate} and against {rival_coord} "
                 f"({rival})", fontsize=11)
    return fig


def _finding_sections(result: AuditResult) -> str:
    if not result.findings:
        return ""
    out = ["<h2>Why each finding is believable</h2>"]
    candidates = _accepted_candidates(result)
    thresholds = [h.get("threshold") for h in result.history]
    open_counts = [len(h.get("trials", [])) for h in result.history]
    for i, (finding, cand) in enumerate(zip(result.findings, candidates)):
        label = finding.get("target", "")
        ev, gain = finding.get("evidence", {}), finding.get("gain", {})
        title = f"{i + 1}. {finding['effect']} on {label}"
        out.append(f"<h3>{html.escape(title)}</h3>")
        if finding.get("meaning"):
            out.append(f"<p><i>{html.escape(finding['meaning'])}.</i></p>")
        threshold = thresholds[i] if i < len(thresholds) else None
        n_open = open_counts[i] if i < len(open_counts) else None
        unit = ""
        fam_before = fam_after = None
        if cand is not None and i + 1 < len(result.fits):
            fam_before = result.fits[i].family(cand.target, cand.sensor)
            fam_after = result.fits[i + 1].family(cand.target, cand.sensor)
            unit = unit_html(fam_before.unit) if fam_before else ""
        because = [f"its score test gives F = {num(ev.get('statistic'), 4)}, p = {pval(ev.get('p_value'))}"
                   + (f" against the step's Bonferroni threshold {pval(threshold)} ({n_open} open candidates)"
                      if threshold is not None else "")]
        if _finite(gain.get("delta_bic")):
            because.append(f"refitted, it changes the BIC by {num(gain['delta_bic'], 4)} (negative: the fit gain "
                           "pays for the extra parameters)")
        if gain.get("heldout_rms_before") is not None:
            because.append(f"it predicts data it was not fitted to: held-out RMS {num(gain['heldout_rms_before'], 3)}"
                           f" &rarr; {num(gain.get('heldout_rms_after'), 3)} {unit}")
        out.append("<p>Accepted because " + "; ".join(because) + ".</p>")
        if finding.get("ambiguous_with"):
            out.append(_ambiguity_box(finding))
            if fam_before is not None:
                out += _ambiguity_figures(finding, cand, fam_before)
        if fam_before is not None and fam_after is not None:
            fig = finding_figure(fam_before, fam_after, cand.coordinate, finding["effect"])
            uri = figure_to_data_uri(fig)
            coords = ", ".join(plot_coordinates(cand.coordinate, fam_before))
            out.append(f"<figure><img src=\"{uri}\" alt=\"{html.escape(title)}: residuals before and after\">"
                       f"<figcaption>{html.escape(label)} residuals against {html.escape(coords)}: top, the model "
                       f"before the finding ({html.escape(_model_name(result, i))}); bottom, with "
                       f"{html.escape(finding['effect'])} added. Same y scale; RMS {num(fam_before.rms, 3)} &rarr; "
                       f"{num(fam_after.rms, 3)} {unit}.</figcaption></figure>")
        else:
            out.append("<p class=\"small\">(No residual family to plot for this finding.)</p>")
    return "\n".join(out)


def _ambiguity_figures(finding: dict, cand: Candidate, before: ResidualFamily) -> list[str]:
    out = []
    for rival in finding.get("ambiguous_with", []):
        effect = str(rival.get("effect", ""))
        coord = rival_coordinate(effect, before)
        if coord is None or (rival.get("target") and rival["target"] != before.label):
            continue
        fig = ambiguity_figure(before, cand.coordinate, effect, coord)
        if fig is None:
            continue
        out.append(f"<figure><img src=\"{figure_to_data_uri(fig)}\" alt=\"{html.escape(finding['effect'])} "
                   f"against {html.escape(effect)}\"><figcaption>Why the data cannot decide: the residual the "
                   f"earlier model left, against the coordinate of {html.escape(finding['effect'])} "
                   f"({html.escape(cand.coordinate)}) and of {html.escape(effect)} ({html.escape(coord)}). When the "
                   "two coordinates move together over the recording, a dependence on one is a dependence on the "
                   "other.</figcaption></figure>")
    return out


def _model_name(result: AuditResult, i: int) -> str:
    added = [f["effect"] for f in result.findings[:i]]
    return " + ".join([result.base_model] + added)


# --- diagnostics and history --------------------------------------------------------------------------------------

def _p_cell(p, label: str = "") -> str:
    cls = ""
    if _finite(p):
        cls = " pbad" if p < P_STRONG else (" pwarn" if p < P_WEAK else "")
    extra = f" <span class=\"small\">{label}</span>" if label else ""
    return f"<td class=\"num{cls}\">{pval(p)}{extra}</td>"


def _diagnostics_section(fit: Fit) -> str:
    rows, n_p = [], 0
    for fam in fit.families:
        for d in diagnose(fam):
            n_p += 6
            unit = unit_html(d["unit"])
            lin = (f"<td>{html.escape(d['linear_coordinate'] or '–')}</td>"
                   f"<td class=\"num\">{num(d['linear_slope'], 3)}</td>" + _p_cell(d["linear_p"]))
            anova = f"<td>{html.escape(d['anova_coordinate'] or '–')}</td>" + _p_cell(
                d["anova_p"], f"{d['anova_bins']} bins" if d["anova_bins"] else "")
            rows.append(f"<tr><td>{html.escape(d['family'])}</td><td>{html.escape(d['component'])}</td>"
                        f"<td class=\"num\">{d['n']}</td><td class=\"num\">{num(d['mean'], 3)} {unit}</td>"
                        + _p_cell(d["mean_p"]) + f"<td class=\"num\">{num(d['rms'], 3)} {unit}</td>"
                        + _p_cell(d["ljung_box_p"], f"h={d['ljung_box_lags']}")
                        + _p_cell(d["normality_p"], "SW" if d["normality_test"] == "shapiro" else "DP")
                        + lin + anova
                        + f"<td class=\"num\">{num(d['period_s'], 3)}</td>" + _p_cell(d["period_fap"]) + "</tr>")
    head = ("<tr><th rowspan=\"2\">family</th><th rowspan=\"2\">comp.</th><th rowspan=\"2\">n</th>"
            "<th colspan=\"2\">mean (t-test p)</th><th rowspan=\"2\">RMS</th><th rowspan=\"2\">Ljung-Box p</th>"
            "<th rowspan=\"2\">normality p</th><th colspan=\"3\">strongest linear dependence</th>"
            "<th colspan=\"2\">strongest binned (ANOVA) dependence</th>"
            "<th colspan=\"2\">periodic term in time</th></tr>"
            "<tr><th>mean</th><th>p</th><th>coordinate</th>"
            "<th>slope<br><span class=\"small\">per coord. unit</span></th><th>p (adj.)</th>"
            "<th>coordinate</th><th>p (adj.)</th><th>period [s]</th><th>false-alarm p</th></tr>")
    return ("<h2>Residual diagnostics of the final model</h2>\n"
            "<p class=\"small\">What the final model still leaves. Tests run on the whitened residuals (scale-free); "
            "mean, RMS and slope are physical. Ljung-Box on the time-ordered residuals (h lags); normality: "
            "D'Agostino-Pearson (DP, n &ge; 8) or Shapiro-Wilk (SW); dependence: the coordinate with the smallest "
            "p-value, Bonferroni-adjusted over the coordinates tried; ANOVA over quantile bins catches a "
            "dependence a straight line misses; the periodic term is the strongest Lomb–Scargle period of the "
            "residual in time with Baluev's false-alarm probability. Shaded: p &lt; 0.01 (amber), p &lt; 0.001 (red). With "
            f"{n_p} p-values here, about {num(0.01 * n_p, 2)} amber cells are expected from noise alone.</p>\n"
            f"<table>{head}{''.join(rows)}</table>")


def _history_section(result: AuditResult) -> str:
    if not result.history:
        return ""
    keys: list[str] = []
    for step in result.history:
        for t in step.get("trials", []):
            if t["candidate"] not in keys:
                keys.append(t["candidate"])
    accepted_at = {step.get("accepted"): step["step"] for step in result.history if step.get("accepted")}
    head = "<tr><th>candidate</th>" + "".join(
        f"<th>step {step['step']}<br><span class=\"small\">threshold {pval(step.get('threshold'))}</span></th>"
        for step in result.history) + "</tr>"
    rows = []
    for key in keys:
        cells = []
        for step in result.history:
            trial = next((t for t in step.get("trials", []) if t["candidate"] == key), None)
            if trial is None:
                in_model = key in accepted_at and accepted_at[key] < step["step"]
                cells.append("<td class=\"inmodel\">in model</td>" if in_model else "<td></td>")
                continue
            text = f"{pval(trial['p_value'])} <span class=\"small\">F {num(trial['F'], 3)}</span>"
            if step.get("accepted") == key:
                cells.append(f"<td class=\"num hist acc\">&#10004; {text}</td>")
            elif _finite(trial["p_value"]) and trial["p_value"] < step.get("threshold", 0):
                cells.append(f"<td class=\"num hist sig\">{text}</td>")
            else:
                cells.append(f"<td class=\"num hist\">{text}</td>")
        rows.append(f"<tr><td>{html.escape(key)}</td>{''.join(cells)}</tr>")
    last = result.history[-1]
    if last.get("accepted"):
        stop = "the search stopped at its limit on the number of findings."
    elif any(_finite(t["p_value"]) and t["p_value"] < last.get("threshold", 0) for t in last.get("trials", [])):
        stop = ("the search stopped: the significant candidates left did not lower both the BIC and the held-out "
                "residual.")
    else:
        stop = "the search stopped: no candidate left is significant."
    return ("<h2>Search history</h2>\n"
            "<p class=\"small\">Score-test p-value (and F) of every open candidate at each step "
            "(candidate = effect@sensor:target). Green &#10004;: accepted; amber: significant (p below the "
            "Bonferroni threshold "
            f"&alpha;/m) but not the one accepted; grey: already in the model. After the last step, {stop}</p>\n"
            f"<table>{head}{''.join(rows)}</table>")


# --- extras -------------------------------------------------------------------------------------------------------

def _cell(value) -> str:
    if isinstance(value, dict):
        return "; ".join(f"{html.escape(str(k))}: {_cell(v)}" for k, v in value.items())
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_cell(v) for v in np.asarray(value, dtype=object).ravel()) + "]"
    if isinstance(value, str):
        return html.escape(value)
    return num(value)


def dict_table(rows: list[dict]) -> str:
    """An HTML table of a list of dicts; columns: every key, in order of first appearance."""
    rows = [r for r in rows if isinstance(r, dict)]
    if not rows:
        return ""
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    head = "".join(f"<th>{html.escape(str(c).replace('_', ' '))}</th>" for c in columns)

    def cell(column, value):
        if _finite(value):
            return f"<td class=\"num\">{_cell(value)}</td>"
        if column == "unit" and isinstance(value, str):
            return f"<td>{unit_html(value)}</td>"
        return f"<td>{_cell(value)}</td>"

    body = "".join("<tr>" + "".join(cell(c, r.get(c)) for c in columns) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _noise_section(items: list[dict]) -> str:
    out = ["<h2>Noise</h2>"]
    for item in items:
        out.append(f"<h3>{html.escape(str(item.get('title', 'noise audit')))}</h3>")
        if item.get("text"):
            out.append(f"<p>{html.escape(str(item['text']))}</p>")
        uri = None
        if item.get("figure") is not None:
            uri = figure_to_data_uri(item["figure"])
        elif item.get("png_path"):
            uri = png_to_data_uri(Path(item["png_path"]).read_bytes())
        if uri:
            out.append(f"<figure><img src=\"{uri}\" alt=\"{html.escape(str(item.get('title', 'noise')))}\"></figure>")
        if item.get("table"):
            out.append(dict_table(item["table"]))
    return "\n".join(out)


def _key_starting(row: dict, prefix: str, prefer: str = "") -> str | None:
    keys = [k for k in row if str(k).startswith(prefix)]
    preferred = [k for k in keys if prefer and prefer in str(k)]
    return (preferred or keys or [None])[0]


def _simulation_section(rows: list[dict]) -> str:
    sentences = []
    for r in rows:
        if not isinstance(r, dict):
            continue
        mb, sb = _key_starting(r, "measured_base"), _key_starting(r, "simulated_base")
        sf, mf = _key_starting(r, "simulated_final", prefer="base_fit"), _key_starting(r, "measured_final")
        if not (mb and sb and _finite(r.get(mb)) and _finite(r.get(sb))):
            continue
        unit = unit_html(r.get("unit")) if isinstance(r.get("unit"), str) else ""
        text = (f"{html.escape(str(r.get('family', '')))}: the base model's simulation predicts a residual of "
                f"{num(r[sb], 3)} {unit} where the measurement shows {num(r[mb], 3)}")
        if sf and _finite(r.get(sf)):
            text += f"; the extended model's simulation predicts {num(r[sf], 3)}"
        if mf and _finite(r.get(mf)):
            text += f" (after the extension the measurement leaves {num(r[mf], 3)})"
        sentences.append(text + ".")
    intro = ("<p class=\"small\">The recording's protocol simulated with the base model and with the extended "
             "model, analysed like the measurement (residual RMS per family). A model that is right predicts the "
             "residual the measurement shows; where the base model's simulation predicts far less than measured, "
             "the base model misses something, and the extended model's simulation should close the gap.</p>")
    listing = "<ul>" + "".join(f"<li>{s}</li>" for s in sentences) + "</ul>" if sentences else ""
    return f"<h2>Measured against simulated</h2>\n{intro}\n{listing}\n{dict_table(rows)}"
