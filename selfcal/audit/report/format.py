"""Numbers, p-values, units and estimates as the report shows them (HTML entities, engineering exponents).

Every function returns HTML text (``&minus;``, ``&times;10<sup>..</sup>``) except :func:`unit_tex` and
:func:`tex_num`, which write matplotlib mathtext for figure labels.  The templates use these as Jinja filters.
"""
from __future__ import annotations

import html
import math
import re

import numpy as np

# estimate keys shown in a unit engineers read off datasheets: key -> (unit shown, factor from the JSON unit)
DISPLAY_UNITS = {"scale": ("ppm", 1e6), "angles": ("mrad", 1e3), "dt_s": ("ms", 1e3), "r_m": ("mm", 1e3),
                 "tau_s": ("s", 1.0)}
AXES3 = ("x", "y", "z")
ACCEL_ANGLES = ("yz", "zy", "zx")  # Tedaldi's upper-triangular non-orthogonality angles
OFF_DIAGONAL = ("xy", "xz", "yx", "yz", "zx", "zy")  # full-matrix off-diagonal entries, row-major
P_STRONG, P_WEAK = 1e-3, 1e-2  # shading levels of p-values in the diagnostics table


def finite(x) -> bool:
    """A real, finite number (not None, not a string, not NaN or inf)."""
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
        return minus(f"{x:.{digits}g}")
    if 10**digits <= a < 1e6:
        return minus(f"{x:.0f}")
    return _sci(x, digits)


def pval(p) -> str:
    """A p-value with 2 significant digits (below 1e-300 shown as a bound)."""
    if p is None or not finite(p):
        return "&ndash;"
    p = float(p)
    if p < 1e-300:
        return "&lt; 10<sup>&minus;300</sup>"
    if p >= 1e-3:
        return f"{p:.2g}"
    return _sci(p, 2)


def p_class(p) -> str:
    """CSS classes that shade a p-value cell: `` pbad`` below P_STRONG, `` pwarn`` below P_WEAK, else none."""
    if not finite(p):
        return ""
    return " pbad" if p < P_STRONG else (" pwarn" if p < P_WEAK else "")


def signed(x) -> str:
    """A number with its sign always shown (``+1.7``, ``&minus;2``)."""
    x = float(x)
    return ("+" if x >= 0 else "") + num(x, 3)


def _sci(x: float, digits: int) -> str:
    exponent = int(math.floor(math.log10(abs(x))))
    mantissa = x / 10.0**exponent
    if round(abs(mantissa), digits - 1) >= 10.0:
        mantissa, exponent = mantissa / 10.0, exponent + 1
    text = f"{mantissa:.{digits - 1}f}".rstrip("0").rstrip(".")
    return f"{minus(text)}&times;10<sup>{minus(str(exponent))}</sup>"


def minus(s: str) -> str:
    """Hyphens as typographic minus signs."""
    return s.replace("-", "&minus;")


def unit_html(unit: str | None) -> str:
    """``m s^-2`` -> ``m s<sup>-2</sup>``."""
    if not unit:
        return ""
    return re.sub(r"\^(-?\d+)", lambda m: f"<sup>{minus(m.group(1))}</sup>", html.escape(unit))


def unit_tex(unit: str | None) -> str:
    """``m s^-2`` -> ``m s$^{-2}$`` for matplotlib labels."""
    if not unit:
        return ""
    return re.sub(r"\^(-?\d+)", r"$^{\1}$", unit)


def tex_num(x: float, digits: int = 3) -> str:
    """A number for a matplotlib label: ``1.23 \\times 10^{-5}`` in mathtext when it needs an exponent."""
    if not math.isfinite(x) or x == 0.0 or 1e-3 <= abs(x) < 1e4:
        return f"{x:.{digits}g}"
    exponent = int(math.floor(math.log10(abs(x))))
    mantissa = f"{x / 10.0**exponent:.{digits - 1}f}".rstrip("0").rstrip(".")
    return f"${mantissa}\\times10^{{{exponent}}}$"


def engineering_exponent(values) -> int:
    """Power of ten (multiple of 3) that brings the largest |value| into [1, 1000)."""
    finite_abs = np.abs(np.asarray([v for v in np.ravel(values) if finite(v)], dtype=float))
    finite_abs = finite_abs[finite_abs > 0]
    if finite_abs.size == 0:
        return 0
    e = int(math.floor(math.log10(finite_abs.max())))
    return 3 * (e // 3)


def value_html(value) -> str:
    """Any JSON-like value inline: dicts as ``key: value; ...``, lists in brackets, strings escaped, numbers
    by :func:`num`."""
    if isinstance(value, dict):
        return "; ".join(f"{html.escape(str(k))}: {value_html(v)}" for k, v in value.items())
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(value_html(v) for v in np.asarray(value, dtype=object).ravel()) + "]"
    if isinstance(value, str):
        return html.escape(value)
    return num(value)


def _value_sigma(v, s) -> str:
    """``value ± sigma``: sigma to 2 significant digits, the value to the same decimal place."""
    if not finite(v):
        return num(v)
    if s is None or not finite(s) or float(s) <= 0:
        return num(v)
    s = float(s)
    decimals = int(np.clip(1 - math.floor(math.log10(s)), 0, 8))
    return f"{minus(f'{float(v):.{decimals}f}')}&nbsp;&plusmn;&nbsp;{s:.{decimals}f}"


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
            lines.append(f"<div>{html.escape(key)}: {value_html(value)}</div>")
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
        exponent = engineering_exponent(values)
        if 1e-2 <= largest < 1e4 or (-3 <= exponent <= 3 and key in DISPLAY_UNITS):
            exponent = 0  # readable as it is
        if exponent:
            values, sigmas = values / 10.0**exponent, sigmas / 10.0**exponent
        unit = _estimate_unit(key, estimate, effect)
        bracket = " ".join(t for t in (f"&times;10<sup>{minus(str(exponent))}</sup>" if exponent else "",
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
