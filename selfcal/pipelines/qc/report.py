"""The QC report of ``selfcal qc``: a colour-coded deviation image (PNG), one self-contained HTML file, Markdown.

The deviation image views the scan along its direction of least extent (the third principal axis) and shows,
per pixel, the mean signed deviation from the reference mesh on a diverging colour map centred on zero (blue:
inside / below the reference, red: outside / above); the colour range is the deviation tolerance where the
spec gives one, else the 99th percentile of |d|.  A histogram of the deviations sits next to it.  Figures are
rendered with matplotlib's Agg canvas (no pyplot state); files are written atomically.
"""
from __future__ import annotations

import datetime as _dt
import html
import io
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from selfcal.audit.report import CSS, png_to_data_uri
from selfcal.io.atomic import atomic_write_bytes, atomic_write_text
from selfcal.pipelines.qc.checks import QCResult

VERDICT_COLOUR = {"pass": "#cdebd0", "fail": "#f6c9c4", "incomplete": "#fbe7c0", "reported": "#f6f8fa",
                  "cannot be vouched for": "#e8c4f0"}
IMAGE_PIXELS = 600  # long side of the rasterised deviation map
IMAGE_MAX_POINTS = 2_000_000


LABEL_OFFSETS_PT = ((6, 6), (6, -6), (-6, 6), (-6, -6))  # up-right first, then the other three corners


def label_offsets_pt(centres: np.ndarray, near: float) -> list[tuple[int, int]]:
    """An offset (points) for the label of each centre (N, 2): labels of centres closer than ``near`` (same
    unit as the centres) to one already placed go to a corner that one does not use, so they do not overlap."""
    chosen: list[tuple[int, int]] = []
    for i, c in enumerate(centres):
        used = {chosen[j] for j in range(i) if np.linalg.norm(centres[j] - c) < near}
        chosen.append(next((o for o in LABEL_OFFSETS_PT if o not in used), LABEL_OFFSETS_PT[i % 4]))
    return chosen


def principal_view(points: np.ndarray, values: np.ndarray):
    """Mean of ``values`` per pixel of the points viewed along their direction of least extent (third principal
    axis, from a subsample): (image (rows, cols), extent (lo_u, hi_u, lo_v, hi_v), mean point, axes (3, 2))."""
    mean = points.mean(axis=0)
    # principal axes from a subsample (the covariance of 10 M points needs no more than 200 k of them)
    sub = points[:: max(1, len(points) // 200_000)] - mean
    _, _, vt = np.linalg.svd(sub, full_matrices=False)
    # SVD signs are arbitrary: turn each axis so that its largest component is positive (a plate in the
    # xy plane is then shown with x to the right and y up, not mirrored)
    vt = vt * np.sign(vt[np.arange(3), np.argmax(np.abs(vt), axis=1)])[:, None]
    # einsum, not BLAS: a threaded (N, 3) x (3, 2) product stalls for seconds on a busy shared machine
    axes = vt[:2].T
    uv = np.einsum("ij,jk->ik", points, axes) - mean @ axes
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    extent = np.maximum(hi - lo, 1e-9)
    shape = np.maximum(np.round(IMAGE_PIXELS * extent / extent.max()).astype(int), 1)
    ix = np.minimum(((uv - lo) / extent * shape).astype(int), shape - 1)
    flat = ix[:, 1] * shape[0] + ix[:, 0]
    n = np.bincount(flat, minlength=shape[0] * shape[1])
    s = np.bincount(flat, weights=values, minlength=shape[0] * shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        image = (s / n).reshape(shape[1], shape[0])
    return image, (lo[0], hi[0], lo[1], hi[1]), mean, axes


def deviation_png(result: QCResult, dpi: int = 110) -> bytes | None:
    """PNG bytes of the deviation map and histogram; None without a reference (or no point on it)."""
    dev = result.deviation
    if dev is None or dev.n_evaluated == 0:
        return None
    # at most IMAGE_MAX_POINTS (a regular stride): the map has ~2e5 pixels, a few points per pixel suffice
    step = max(1, len(dev.points_m) // IMAGE_MAX_POINTS)
    pts, d = dev.points_m[::step], dev.distances_m[::step]
    image, (lo_u, hi_u, lo_v, hi_v), mean, axes = principal_view(pts, d)
    lo, hi = np.array([lo_u, lo_v]), np.array([hi_u, hi_v])
    extent = np.maximum(hi - lo, 1e-9)
    tol = result.spec.tolerances
    limit = tol.deviation_p95_m or tol.deviation_max_m or float(np.percentile(np.abs(d), 99)) or 1e-6
    mm = 1e3
    fig = Figure(figsize=(12, 4.8), layout="constrained")
    ax, hx = fig.subplots(1, 2, width_ratios=[2.6, 1])
    im = ax.imshow(image * mm, origin="lower", cmap="RdBu_r", vmin=-limit * mm, vmax=limit * mm,
                   extent=(lo[0], hi[0], lo[1], hi[1]), interpolation="nearest")
    ax.set_xlabel("first principal axis [m]")
    ax.set_ylabel("second principal axis [m]")
    ax.set_title("signed deviation from the reference (mean per pixel)")
    centres = np.array([(s.centre_fit.center_m - mean) @ axes for s in result.spheres]).reshape(-1, 2)
    for sphere, c, (dx, dy) in zip(result.spheres, centres, label_offsets_pt(centres, 0.08 * extent.max())):
        ax.plot(*c, "k+", ms=6, mew=1)
        ax.annotate(sphere.name, c, xytext=(dx, dy), textcoords="offset points", color="k", fontsize=8,
                    ha="left" if dx > 0 else "right", va="bottom" if dy > 0 else "top",
                    bbox={"facecolor": "white", "alpha": 0.7, "edgecolor": "none", "pad": 0.5})
    cbar = fig.colorbar(im, ax=ax, fraction=0.04)
    cbar.set_label("deviation [mm]")
    hx.hist(np.clip(d * mm, -3 * limit * mm, 3 * limit * mm), bins=120, color="#4a7ab5")
    for v in (-limit, limit):
        hx.axvline(v * mm, color="#c0392b", lw=1, ls="--")
    hx.set_xlabel("deviation [mm] (clipped at 3x range)")
    hx.set_ylabel("points")
    hx.set_title(f"RMS {dev.rms_m * mm:.3g} mm\np95 |d| {dev.p95_abs_m * mm:.3g} mm")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def sigma_png(result: QCResult, dpi: int = 110) -> bytes | None:
    """PNG bytes of the predicted-accuracy map: the bound ``z sigma`` per pixel (mean), the tolerance marked on
    the colour bar, and its histogram; None when the scan carries no predicted accuracy."""
    pred = result.prediction
    if pred is None:
        return None
    step = max(1, len(pred.points_m) // IMAGE_MAX_POINTS)
    bound = pred.z * pred.sigma_m[::step]
    image, extent, _, _ = principal_view(pred.points_m[::step], bound)
    mm = 1e3
    top = max(float(np.max(bound)), pred.tolerance_m or 0.0) * mm
    fig = Figure(figsize=(12, 4.8), layout="constrained")
    ax, hx = fig.subplots(1, 2, width_ratios=[2.6, 1])
    im = ax.imshow(image * mm, origin="lower", cmap="viridis", vmin=0.0, vmax=top, extent=extent,
                   interpolation="nearest")
    ax.set_xlabel("first principal axis [m]")
    ax.set_ylabel("second principal axis [m]")
    ax.set_title(f"predicted {pred.confidence:.0%} error bound of each point (mean per pixel)")
    cbar = fig.colorbar(im, ax=ax, fraction=0.04)
    cbar.set_label("bound [mm]")
    hx.hist(bound * mm, bins=120, color="#4a7ab5")
    if pred.tolerance_m is not None:
        cbar.ax.axhline(pred.tolerance_m * mm, color="#c0392b", lw=2)
        hx.axvline(pred.tolerance_m * mm, color="#c0392b", lw=1, ls="--")
        hx.set_title(f"{pred.fraction_unvouched:.1%} of points beyond {pred.tolerance_m * mm:.3g} mm")
    hx.set_xlabel("bound [mm]")
    hx.set_ylabel("points")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def _mm(x) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x * 1e3:.4g}"


def _value(c) -> str:
    if c.value is None:
        return "-"
    return f"{c.value:.4g}" if c.unit == "fraction" else _mm(c.value)


def _tol(c) -> str:
    if c.tolerance is None:
        return "-"
    return f">= {c.tolerance:.4g}" if c.unit == "fraction" else f"{c.tolerance * 1e3:.4g}"


def _sphere_rows(result: QCResult) -> list[list[str]]:
    rows = []
    for s in result.spheres:
        c, sig = s.centre_fit.center_m, s.centre_fit.center_sigma_m
        rows.append([s.name, ", ".join(f"{x:.5f}" for x in c), ", ".join(f"{x * 1e3:.3g}" for x in sig),
                     f"{s.fit.radius_m:.5f} +- {s.fit.radius_sigma_m * 1e3:.2g} mm", _mm(s.form_error_m),
                     _mm(s.size_error_m), _mm(s.fit.rms_m), str(s.fit.n_points),
                     f"{s.fit.coverage.cap_half_angle_deg:.0f}" + (" (one-sided)" if s.one_sided else ""),
                     f"{s.normal_consistency:.0%}"])
    return rows


SPHERE_HEADER = ["sphere", "centre [m]", "centre 1-sigma [mm]", "radius [m]", "PF [mm]", "PS [mm]",
                 "RMS [mm]", "points", "cap [deg]", "radial normals"]
CHECK_HEADER = ["check", "value [mm]", "tolerance [mm]", "result", "note"]


def _prediction_text(result: QCResult) -> str:
    p = result.prediction.to_json()
    text = (f"The scan carries its predicted 1-sigma per point (from the correction's posterior): median "
            f"{_mm(p['sigma_median_m'])} mm, p95 {_mm(p['sigma_p95_m'])} mm, max {_mm(p['sigma_max_m'])} mm; "
            f"{p['confidence']:.0%} bound = {p['bound_factor']:.3g} sigma.")
    if p["tolerance_m"] is not None:
        text += (f" {p['fraction_unvouched']:.2%} of the points have a bound beyond the point tolerance "
                 f"{_mm(p['tolerance_m'])} mm (allowed: {result.spec.prediction.max_fraction_unvouched:.2%}).")
    return text


def render_markdown(result: QCResult, image_name: str | None = None, sigma_image_name: str | None = None) -> str:
    """The report as Markdown (the deviation image referenced by file name)."""
    lines = [f"# selfcal QC: {Path(result.scan).name}", "",
             f"**Verdict: {result.verdict.upper()}**", "",
             f"- scan: `{result.scan}` ({result.n_points} points"
             + (f", {result.n_nonfinite} non-finite left out" if result.n_nonfinite else "") + ")",
             f"- reference: `{result.reference}`" if result.reference else "- reference: none",
             f"- run: {_dt.datetime.now().isoformat(timespec='seconds')}, {result.seconds['total']:.1f} s", "",
             "## Checks", "", "| " + " | ".join(CHECK_HEADER) + " |", "|" + "---|" * len(CHECK_HEADER)]
    for c in result.checks:
        lines.append(f"| {c.name} | {_value(c)} | {_tol(c)} | {c.status} | {c.note} |")
    if result.prediction is not None:
        lines += ["", "## Predicted accuracy", "", _prediction_text(result)]
        if sigma_image_name:
            lines += ["", f"![predicted accuracy map]({sigma_image_name})"]
    if result.warnings:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in result.warnings]
    if result.spheres:
        lines += ["", "## Spheres", "", "| " + " | ".join(SPHERE_HEADER) + " |", "|" + "---|" * len(SPHERE_HEADER)]
        lines += ["| " + " | ".join(r) + " |" for r in _sphere_rows(result)]
    if result.planes:
        lines += ["", "## Planes", "", "| plane | normal | points | flatness [mm] | RMS [mm] |", "|---|---|---|---|---|"]
        lines += [f"| {p.name} | {np.round(p.normal, 4).tolist()} | {p.n_points} | {_mm(p.flatness_m)} | {_mm(p.rms_m)} |"
                  for p in result.planes]
    if result.deviation is not None:
        d = result.deviation
        lines += ["", "## Deviation from the reference", "",
                  f"{d.n_evaluated} points evaluated, {d.n_off_reference} farther than "
                  f"{result.spec.reference.max_distance_m} m; mean {_mm(d.mean_m)} mm, RMS {_mm(d.rms_m)} mm, "
                  f"p95 |d| {_mm(d.p95_abs_m)} mm, max |d| {_mm(d.max_abs_m)} mm."]
        if image_name:
            lines += ["", f"![deviation map]({image_name})"]
    return "\n".join(lines) + "\n"


def _table(header, rows, classes=None) -> str:
    out = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    for k, row in enumerate(rows):
        cls = f' class="{classes[k]}"' if classes and classes[k] else ""
        out.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in row) + "</tr>")
    return "\n".join(out) + "</table>"


def render_html(result: QCResult, png: bytes | None, sigma: bytes | None = None) -> str:
    """The report as one self-contained HTML file (the image embedded as base64 PNG)."""
    colour = VERDICT_COLOUR[result.verdict]
    parts = [f"<h1>selfcal QC: {html.escape(Path(result.scan).name)}</h1>",
             f'<div class="summary" style="background:{colour}"><b>Verdict: {result.verdict.upper()}</b> &mdash; '
             f"{sum(c.passed is True for c in result.checks)} passed, {sum(c.passed is False for c in result.checks)} "
             f"failed, {sum(c.status == 'no tolerance' for c in result.checks)} without tolerance, "
             f"{sum(c.value is None for c in result.checks)} not checked "
             "(VDI/VDE 2634-2 figures: PF probing error of form, PS of size (diameter), SD sphere spacing, "
             "F flatness)</div>",
             '<table class="meta">'
             f"<tr><td>scan</td><td>{html.escape(result.scan)} ({result.n_points} points"
             + (f", {result.n_nonfinite} non-finite left out" if result.n_nonfinite else "") + ")</td></tr>"
             f"<tr><td>reference</td><td>{html.escape(result.reference or 'none')}</td></tr>"
             f"<tr><td>run</td><td>{_dt.datetime.now().isoformat(timespec='seconds')}, "
             f"{result.seconds['total']:.1f} s</td></tr></table>",
             "<h2>Checks</h2>",
             _table(CHECK_HEADER, [[c.name, _value(c), _tol(c), c.status, c.note] for c in result.checks],
                    ["acc" if c.passed else "pbad" if c.passed is False else "pwarn" for c in result.checks])]
    if result.prediction is not None:
        parts += ["<h2>Predicted accuracy</h2>", f"<p>{html.escape(_prediction_text(result))}</p>"]
        if sigma:
            parts.append(f'<figure><img alt="predicted accuracy map" src="{png_to_data_uri(sigma)}"><figcaption>'
                         "The predicted error bound of each point; red: the point tolerance.</figcaption></figure>")
    if result.warnings:
        parts += ["<h2>Warnings</h2>", "<ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in result.warnings)
                  + "</ul>"]
    if result.spheres:
        parts += ["<h2>Spheres</h2>", _table(SPHERE_HEADER, _sphere_rows(result))]
    if result.planes:
        parts += ["<h2>Planes</h2>", _table(["plane", "normal", "points", "flatness [mm]", "RMS [mm]"],
                                            [[p.name, np.round(p.normal, 4).tolist(), p.n_points, _mm(p.flatness_m),
                                              _mm(p.rms_m)] for p in result.planes])]
    if result.deviation is not None:
        d = result.deviation
        parts += ["<h2>Deviation from the reference</h2>",
                  f"<p>{d.n_evaluated} points evaluated, {d.n_off_reference} farther than "
                  f"{result.spec.reference.max_distance_m} m; mean {_mm(d.mean_m)} mm, RMS {_mm(d.rms_m)} mm, "
                  f"p95 |d| {_mm(d.p95_abs_m)} mm, max |d| {_mm(d.max_abs_m)} mm.</p>"]
        if png:
            parts.append(f'<figure><img alt="deviation map" src="{png_to_data_uri(png)}"><figcaption>Blue: '
                         "inside / below the reference, red: outside / above.</figcaption></figure>")
    title = html.escape(f"selfcal QC: {Path(result.scan).name}")
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{title}</title>\n<style>{CSS}</style>\n</head>\n<body>\n" + "\n".join(parts)
            + "\n</body>\n</html>\n")


def write_reports(result: QCResult, html_path=None, markdown_path=None, png_path=None) -> dict[str, Path]:
    """Write whichever of the HTML report, Markdown report and deviation PNG are asked for (atomically).

    With a Markdown report and no explicit PNG path the image is written next to it (``<name>.png``).
    """
    written = {}
    sigma = sigma_png(result)
    png = deviation_png(result) if result.deviation is not None else None
    if png is not None and png_path is None and markdown_path is not None:
        png_path = Path(markdown_path).with_suffix(".png")
    if png is not None and png_path is not None:
        written["png"] = atomic_write_bytes(Path(png_path), png)
    if html_path is not None:
        written["html"] = atomic_write_text(Path(html_path), render_html(result, png, sigma))
    if markdown_path is not None:
        image = sigma_image = None
        if "png" in written:
            image = (written["png"].name if written["png"].parent.resolve() == Path(markdown_path).parent.resolve()
                     else str(written["png"]))
        if sigma is not None:  # beside the Markdown, as <name>.sigma.png
            written["sigma_png"] = atomic_write_bytes(Path(markdown_path).with_suffix(".sigma.png"), sigma)
            sigma_image = written["sigma_png"].name
        written["markdown"] = atomic_write_text(Path(markdown_path), render_markdown(result, image, sigma_image))
    return written
