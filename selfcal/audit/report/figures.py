"""The report's figures: matplotlib figures rendered with the Agg canvas (no pyplot, no global state), and the
data URIs that embed them in the page as base64 PNG.

* :func:`finding_figure`: one residual family against the coordinates a finding's signature depends on, before
  and after the finding, on one y scale;
* :func:`ambiguity_figure`: why two causes cannot be told apart (the residual against both coordinates);
* :func:`plot_allan`: the Allan deviation of a noise audit (:mod:`selfcal.audit.noise`) with its predictions.
"""
from __future__ import annotations

import base64
import io
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from selfcal.audit.diagnostics import component_names
from selfcal.audit.engine import ResidualFamily
from selfcal.audit.noise import NoiseAuditResult
from selfcal.audit.report.format import engineering_exponent, tex_num, unit_tex
from selfcal.io.atomic import atomic_write_bytes


def figure_to_data_uri(fig: Figure, dpi: int = 96) -> str:
    """``data:image/png;base64,...`` of a matplotlib figure (rendered by the Agg canvas)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return png_to_data_uri(buf.getvalue())


def png_to_data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


# --- findings -----------------------------------------------------------------------------------------------------

COORDINATE_SETS = {"orientation": ("up_x", "up_y", "up_z"), "rotation of each move": ("rot_x", "rot_y", "rot_z"),
                   "time": ("time_s",), "angular rate": ("angular_rate", "angular rate")}
COORDINATE_LABELS = {"up_x": "gravity direction x (sensor frame)", "up_y": "gravity direction y (sensor frame)",
                     "up_z": "gravity direction z (sensor frame)", "rot_x": "move rotation x [rad]",
                     "rot_y": "move rotation y [rad]", "rot_z": "move rotation z [rad]", "time_s": "time [s]",
                     "angular_rate": "angular rate |w| [rad/s]", "angular rate": "angular rate |w| [rad/s]",
                     "angular_acceleration": "angular acceleration |dw/dt| [rad/s^2]"}
COMPONENT_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2")


def plot_coordinates(coordinate: str, family: ResidualFamily) -> list[str]:
    """The family coordinates a candidate's signature is plotted against (falls back on time)."""
    names = COORDINATE_SETS.get(coordinate, (coordinate,))
    present = [n for n in names if n in family.coordinates]
    if present:
        return present
    return ["time_s"] if "time_s" in family.coordinates else list(family.coordinates)[:1]


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
    exponent = engineering_exponent(stacked)
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
            if row == 0 and effect.startswith("unlisted") and len(after.physical) == len(fam.physical):
                # the library term's share: what the model with it takes out of each residual
                change = (np.asarray(fam.physical, dtype=float) - np.asarray(after.physical, dtype=float)).reshape(
                    len(phys), -1) * factor
                for j in range(change.shape[1]):
                    ax.scatter(x, change[:, j], s=14, marker="x", color="black", linewidths=0.8,
                               label="fitted term" if j == 0 else None)
            if row == 1:
                ax.set_xlabel(COORDINATE_LABELS.get(cname, cname))
            if col == 0:
                ax.set_ylabel(_residual_label(fam, exponent, title))
            ax.text(0.02, 0.96, f"RMS {tex_num(fam.rms)} {unit_tex(fam.unit)}", transform=ax.transAxes, va="top",
                    fontsize=9, bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.5})
    if several:
        fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside right upper", fontsize=9,
                   title="component", title_fontsize=9, markerscale=1.3)
    axes[0, 0].set_ylim(-top, top)
    fig.suptitle(f"{before.label} residual vs {plotted_against(coordinate, coords)}: before and after {effect}",
                 fontsize=11)
    return fig


def plotted_against(coordinate: str, coords: list[str]) -> str:
    """What the x axes show, as a title says it: the effect's coordinate, or what stands in for it when the
    residual does not carry that coordinate (then time, :func:`plot_coordinates`)."""
    shown = ", ".join(COORDINATE_LABELS.get(c, c).split(" [")[0] for c in coords) or coordinate
    if set(coords) & set(COORDINATE_SETS.get(coordinate, (coordinate,))):
        return coordinate
    return f"{shown} ({coordinate} is not a coordinate of this residual)"


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


# --- noise --------------------------------------------------------------------------------------------------------

AXIS_NAMES = ("x", "y", "z")
# per quantity: Allan deviation unit, noise density N unit, random walk K unit (Kalibr's imu.yaml units)
ALLAN_UNITS = {"gyro": ("rad/s", "rad/s/sqrt(Hz)", "rad/s^2/sqrt(Hz)"),
               "accel": ("m/s^2", "m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)")}


def noise_figures(quantity: str, axis) -> str:
    """``N = ... K = ...`` of one axis: white density and random walk of the white + random-walk fit
    (:func:`selfcal.core.allan.avar_white`, :func:`~selfcal.core.allan.avar_random_walk`), Kalibr's pair."""
    fit = axis.extensions["random_walk"].params
    _, n_unit, k_unit = ALLAN_UNITS[quantity]
    return f"N = {fit['white_density']:.3g} {n_unit}\nK = {fit['random_walk']:.3g} {k_unit}"


def allan_table(result: NoiseAuditResult) -> list[dict]:
    """One row per axis: N and K (white + random-walk fit) in Kalibr's units, the best extension and its verdict."""
    _, n_unit, k_unit = ALLAN_UNITS[result.quantity]
    return [{"axis": AXIS_NAMES[a.axis], f"N [{n_unit}]": a.extensions["random_walk"].params["white_density"],
             f"K [{k_unit}]": a.extensions["random_walk"].params["random_walk"], "best extension": a.best,
             "delta BIC": a.delta_bic, "accepted": a.accepted} for a in result.axes]


def plot_allan(result: NoiseAuditResult, path) -> Path:
    """PNG of the measured Allan deviation (68 % chi-square intervals), white-only and extended predictions.

    One panel per axis; the extended prediction is drawn solid when accepted, dotted when rejected.  The legend
    gives the axis's noise density N and random walk K in Kalibr's units (:func:`noise_figures`).  Written
    atomically; matplotlib's Agg canvas is used directly (no global backend change).
    """
    unit = ALLAN_UNITS[result.quantity][0]
    fig = Figure(figsize=(5.0 * len(result.axes), 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    axs = fig.subplots(1, len(result.axes), squeeze=False)[0]
    for ax, a in zip(axs, result.axes):
        c = a.curve
        lo, hi = c.confidence_interval()
        ax.errorbar(c.taus_s, c.adev, yerr=[c.adev - lo, hi - c.adev], fmt="o", ms=3, color="k", capsize=2,
                    label="measured (68 %)")
        tt = np.geomspace(c.taus_s[0], c.taus_s[-1], 200)
        label = "white (declared)" if result.declared_white_density is not None else "white only"
        ax.loglog(tt, a.base.adev(tt), "--", color="tab:blue",
                  label=f"{label}: {100 * a.base_err[1]:.0f} % rms")
        ax.loglog(tt, a.extended.adev(tt), "-" if a.accepted else ":", color="tab:red",
                  label=f"{a.best}: {100 * a.extended_err[1]:.0f} % rms"
                        f"{'' if a.accepted else ' (rejected)'}")
        ax.plot([], [], " ", label=noise_figures(result.quantity, a))  # N and K: legend text, no line
        ax.set_title(f"{result.sensor} {result.quantity} {AXIS_NAMES[a.axis]}  dBIC {a.delta_bic:.0f}")
        ax.set_xlabel("tau [s]")
        ax.set_ylabel(f"Allan deviation [{unit}]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return atomic_write_bytes(path, buf.getvalue())
