"""What each section of the audit report shows, as plain data for its template (``templates/<section>.html``).

Numbers stay numbers and names stay plain text here: the templates escape text and format numbers (the filters
of :mod:`selfcal.audit.report.format`).  Figures arrive as ``data:`` URIs (:mod:`selfcal.audit.report.figures`);
estimates arrive formatted (:func:`~selfcal.audit.report.format.format_estimate`), a table cell of its own.
"""
from __future__ import annotations

import datetime as _dt
from pathlib import Path

from selfcal.audit.diagnostics import diagnose
from selfcal.audit.engine import FAMILY_ALPHA, AuditResult, Candidate, Fit, ResidualFamily, entry_name
from selfcal.audit.report.figures import (ambiguity_figure, figure_to_data_uri, finding_figure, plot_coordinates,
                                          png_to_data_uri, rival_coordinate)
from selfcal.audit.report.format import finite, format_estimate


def page(result: AuditResult, extras: dict | None = None) -> dict:
    """The data of every section of the page (``templates/page.html``); None for a section left out."""
    extras = dict(extras or {})
    return {"header": header(result, extras), "summary": summary(result, extras.get("noise_findings", [])),
            "findings": findings_table(result), "details": finding_details(result),
            "remaining": what_remains(result), "n_rejected": len(result.rejected),
            "diagnostics": diagnostics(result.final_fit), "history": history(result),
            "noise": noise(extras["noise"]) if extras.get("noise") else None,
            "simulation": simulation(extras["simulation"]) if extras.get("simulation") else None}


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


def _model_name(result: AuditResult, i: int) -> str:
    added = [f["effect"] for f in result.findings[:i]]
    return " + ".join([result.base_model] + added)


# --- header, summary, findings ------------------------------------------------------------------------------------

def _family_alpha(result: AuditResult) -> float:
    """The level the search ran at: the first step's threshold times its number of open candidates."""
    if result.history and result.history[0].get("trials"):
        return float(result.history[0]["threshold"]) * len(result.history[0]["trials"])
    return FAMILY_ALPHA


def header(result: AuditResult, extras: dict) -> dict:
    """System, recording, base and final model, number of findings and steps, the search's level, run date."""
    date = extras.get("run_date") or _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return {"system": result.system, "recording": str(extras["recording"]) if extras.get("recording") else None,
            "base_model": _base_description(result), "final_model": result.to_json()["final_model"],
            "n_findings": len(result.findings), "n_steps": len(result.history), "alpha": _family_alpha(result),
            "run_date": str(date)}


def summary(result: AuditResult, noise_findings=()) -> dict:
    """Per residual family, what the base model leaves and what the accepted effects remove; the families no
    effect was accepted on; the residual RMS when nothing was found; the noise-model findings of the Allan
    analysis; the findings the data cannot tell apart from a rival."""
    by_target: dict[str, list[int]] = {}
    for i, finding in enumerate(result.findings):
        by_target.setdefault(finding.get("target", "?"), []).append(i)
    targets = []
    for label, idx in by_target.items():
        base_fam = _family_by_label(result.base_fit, label)
        final_fam = _family_by_label(result.final_fit, label)
        last_gain = result.findings[idx[-1]].get("gain", {})
        targets.append({
            "label": label, "unit": base_fam.unit if base_fam else "",
            "effects": [result.findings[i]["effect"] for i in idx],
            "before": base_fam.rms if base_fam else result.findings[idx[0]]["gain"].get("rms_before"),
            "after": final_fam.rms if final_fam else last_gain.get("rms_after"),
            "heldout": last_gain.get("heldout_rms_after")})
    untouched = []
    if result.findings:
        for fam in result.final_fit.families:
            if fam.label not in by_target:
                base_fam = _family_by_label(result.base_fit, fam.label)
                untouched.append({"label": fam.label, "before": base_fam.rms if base_fam else None, "rms": fam.rms,
                                  "unit": fam.unit})
    noise = [{"effect": f["effect"], "target": f.get("target", ""),
              "rms_before_pct": 100 * f.get("gain", {}).get("rms_before", 0),
              "rms_after_pct": 100 * f.get("gain", {}).get("rms_after", 0)} for f in noise_findings]
    return {"base": _base_description(result), "targets": targets, "untouched": untouched,
            "final_rms": [{"label": f.label, "rms": f.rms, "unit": f.unit} for f in result.final_fit.families],
            "noise_findings": noise,
            "ambiguous": [ambiguity(f) for f in result.findings if f.get("ambiguous_with")]}


def ambiguity(finding: dict) -> dict:
    """An accepted effect and the rivals the data cannot tell apart from it (``delta_bic`` None if not finite)."""
    return {"effect": finding["effect"], "target": finding.get("target", ""),
            "rivals": [{"effect": entry_name(r), "target": str(r["target"]) if r.get("target") else None,
                        "delta_bic": r["delta_bic_vs_accepted"] if finite(r.get("delta_bic_vs_accepted")) else None}
                       for r in finding.get("ambiguous_with") or []]}


def findings_table(result: AuditResult) -> list[dict]:
    """One row per finding, in the order accepted (an empty list when nothing was accepted)."""
    units = {f.label: f.unit for fit in result.fits for f in fit.families}
    rows = []
    for f in result.findings:
        sensor, target = str(f.get("sensor", "")), str(f.get("target", ""))
        rows.append({
            "effect": f["effect"], "meaning": f.get("meaning"), "sensor": sensor, "target": target,
            "quantity": target[len(sensor) + 1:] if target.startswith(f"{sensor}/") else target,
            "estimate": format_estimate(f["effect"], f.get("estimate", {}), f.get("std")),
            "evidence": f.get("evidence", {}), "gain": f.get("gain", {}), "unit": units.get(f.get("target", ""), ""),
            "ambiguity": ambiguity(f) if f.get("ambiguous_with") else None})
    return rows


def what_remains(result: AuditResult) -> dict:
    """The final model's verdict per family and the candidates that were significant but not accepted."""
    reasons = {"bic": "BIC does not fall", "heldout": "does not predict held-out data",
               "implausible": "implausible estimate", "outdone": "outdone by a library term"}
    rows = []
    for label, r in result.remaining.items():
        s = r.get("strongest") or {}
        term = (f"{s['form']} in {s['driver']}" + (f" x {s['second_driver']}" if s.get("second_driver") else "")
                if s else "-")
        rows.append({"label": label, "verdict": r["verdict"], "term": term, "p_value": s.get("p_value"),
                     "whiteness_p": r.get("whiteness_p")})
    tests = {(r.get("strongest") or {}).get("test") for r in result.remaining.values()} - {None}
    rejected = [{"name": entry_name(r),
                 "target": r["target"], "p_value": r["evidence"]["p_value"],
                 "reason": reasons.get(r["reason"], r["reason"]) + (f": {r['why']}" if r.get("why") else "")}
                for r in result.rejected]
    return {"rows": rows, "rejected": rejected, "test": "; ".join(sorted(tests)) or "none"}


# --- why each finding is believable -------------------------------------------------------------------------------

def finding_details(result: AuditResult) -> list[dict] | None:
    """Per finding: its test, BIC and held-out evidence, the rivals' figures and the before/after figure."""
    if not result.findings:
        return None
    out = []
    candidates = _accepted_candidates(result)
    thresholds = [h.get("threshold") for h in result.history]
    open_counts = [len(h.get("trials", [])) for h in result.history]
    for i, (finding, cand) in enumerate(zip(result.findings, candidates)):
        label = finding.get("target", "")
        ev, gain = finding.get("evidence", {}), finding.get("gain", {})
        fam_before = fam_after = None
        if cand is not None and i + 1 < len(result.fits):
            fam_before = result.fits[i].family(cand.target, cand.sensor)
            fam_after = result.fits[i + 1].family(cand.target, cand.sensor)
        item = {"title": f"{i + 1}. {finding['effect']} on {label}", "label": label, "effect": finding["effect"],
                "meaning": finding.get("meaning"), "statistic": ev.get("statistic"), "p_value": ev.get("p_value"),
                "threshold": thresholds[i] if i < len(thresholds) else None,
                "n_open": open_counts[i] if i < len(open_counts) else None,
                "delta_bic": gain["delta_bic"] if finite(gain.get("delta_bic")) else None,
                "heldout": ((gain["heldout_rms_before"], gain.get("heldout_rms_after"))
                            if gain.get("heldout_rms_before") is not None else None),
                "unit": fam_before.unit if fam_before else "",
                "ambiguity": ambiguity(finding) if finding.get("ambiguous_with") else None,
                "ambiguity_figures": [], "figure": None}
        if item["ambiguity"] and fam_before is not None:
            item["ambiguity_figures"] = _ambiguity_figures(finding, cand, fam_before)
        if fam_before is not None and fam_after is not None:
            name = (finding["effect"] if finding["effect"] != "unlisted"
                    else f"unlisted: {finding['form']} in {finding['driver']}")
            fig = finding_figure(fam_before, fam_after, cand.coordinate, name)
            item["figure"] = {"uri": figure_to_data_uri(fig), "coordinates": plot_coordinates(cand.coordinate,
                                                                                                fam_before),
                              "model_name": _model_name(result, i), "rms_before": fam_before.rms,
                              "rms_after": fam_after.rms}
        out.append(item)
    return out


def _ambiguity_figures(finding: dict, cand: Candidate, before: ResidualFamily) -> list[dict]:
    """The residual against the accepted effect's and each rival's coordinate, for the rivals on this family."""
    out = []
    for rival in finding.get("ambiguous_with", []):
        effect = str(rival.get("effect", ""))
        coord = rival_coordinate(effect, before)
        if coord is None or (rival.get("target") and rival["target"] != before.label):
            continue
        fig = ambiguity_figure(before, cand.coordinate, effect, coord)
        if fig is None:
            continue
        out.append({"uri": figure_to_data_uri(fig), "effect": finding["effect"], "coordinate": cand.coordinate,
                    "rival": effect, "rival_coordinate": coord})
    return out


# --- diagnostics and history --------------------------------------------------------------------------------------

def diagnostics(fit: Fit) -> list[dict]:
    """The residual diagnostics of every family of the final fit (:func:`selfcal.audit.diagnostics.diagnose`)."""
    return [d for fam in fit.families for d in diagnose(fam)]


def history(result: AuditResult) -> dict | None:
    """Every candidate's trial at every step: ``state`` is ``accepted``, ``significant`` (p below the step's
    threshold but not accepted), ``tried``, ``in_model`` (accepted at an earlier step) or ``absent``; ``stop``
    says why the search ended (``limit``, ``not_predictive`` or ``nothing_significant``)."""
    if not result.history:
        return None
    keys: list[str] = []
    for step in result.history:
        for t in step.get("trials", []):
            if t["candidate"] not in keys:
                keys.append(t["candidate"])
    accepted_at = {step.get("accepted"): step["step"] for step in result.history if step.get("accepted")}
    rows = []
    for key in keys:
        cells = []
        for step in result.history:
            trial = next((t for t in step.get("trials", []) if t["candidate"] == key), None)
            if trial is None:
                in_model = key in accepted_at and accepted_at[key] < step["step"]
                cells.append({"state": "in_model" if in_model else "absent"})
                continue
            if step.get("accepted") == key:
                state = "accepted"
            elif finite(trial["p_value"]) and trial["p_value"] < step.get("threshold", 0):
                state = "significant"
            else:
                state = "tried"
            cells.append({"state": state, "p_value": trial["p_value"], "F": trial["F"]})
        rows.append({"candidate": key, "cells": cells})
    last = result.history[-1]
    if last.get("accepted"):
        stop = "limit"
    elif any(finite(t["p_value"]) and t["p_value"] < last.get("threshold", 0) for t in last.get("trials", [])):
        stop = "not_predictive"
    else:
        stop = "nothing_significant"
    return {"steps": [{"step": s["step"], "threshold": s.get("threshold")} for s in result.history],
            "rows": rows, "stop": stop}


# --- extras -------------------------------------------------------------------------------------------------------

def dict_table(rows: list) -> dict | None:
    """A list of dicts as a table: columns are every key, in order of first appearance; None without a dict."""
    rows = [r for r in rows if isinstance(r, dict)]
    if not rows:
        return None
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    return {"columns": columns, "rows": [[(c, r.get(c)) for c in columns] for r in rows]}


def noise(items: list[dict]) -> list[dict]:
    """The noise audits (Allan deviation): title, text, figure (a Figure or a PNG file) and table of each."""
    out = []
    for item in items:
        uri = None
        if item.get("figure") is not None:
            uri = figure_to_data_uri(item["figure"])
        elif item.get("png_path"):
            uri = png_to_data_uri(Path(item["png_path"]).read_bytes())
        out.append({"title": str(item.get("title", "noise audit")), "alt": str(item.get("title", "noise")),
                    "text": str(item["text"]) if item.get("text") else None, "uri": uri,
                    "table": dict_table(item["table"]) if item.get("table") else None,
                    "has_table": bool(item.get("table"))})
    return out


def _key_starting(row: dict, prefix: str, prefer: str = "") -> str | None:
    keys = [k for k in row if str(k).startswith(prefix)]
    preferred = [k for k in keys if prefer and prefer in str(k)]
    return (preferred or keys or [None])[0]


def simulation(rows: list[dict]) -> dict:
    """Measured against simulated residual RMS: one sentence per family where both base values are numbers,
    and the whole table."""
    sentences = []
    for r in rows:
        if not isinstance(r, dict):
            continue
        mb, sb = _key_starting(r, "measured_base"), _key_starting(r, "simulated_base")
        sf, mf = _key_starting(r, "simulated_final", prefer="base_fit"), _key_starting(r, "measured_final")
        if not (mb and sb and finite(r.get(mb)) and finite(r.get(sb))):
            continue
        axis = str(r.get("axis") or "")
        sentences.append({"family": f"{r.get('family', '')} {axis}".strip(),  # one sentence per axis: name it
                          "unit": r.get("unit") if isinstance(r.get("unit"), str) else "",
                          "measured_base": r[mb], "simulated_base": r[sb],
                          "simulated_final": r[sf] if sf and finite(r.get(sf)) else None,
                          "measured_final": r[mf] if mf and finite(r.get(mf)) else None})
    return {"sentences": sentences, "table": dict_table(rows)}
