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

The page and each section are Jinja2 templates (``templates/*.html``, the style in ``templates/style.css``);
:mod:`.sections` gathers what each section shows, :mod:`.format` writes numbers and units (the templates'
filters), :mod:`.figures` draws the matplotlib figures (Agg canvas, no pyplot, no global state), embedded as
base64 PNG.  There is no JavaScript.  The file is written atomically.
"""
from __future__ import annotations

import html
from importlib import resources
from pathlib import Path

import jinja2

from selfcal.audit.engine import AuditResult
from selfcal.audit.report import sections
from selfcal.audit.report.figures import allan_table, figure_to_data_uri, plot_allan, png_to_data_uri
from selfcal.audit.report.format import finite, format_estimate, num, p_class, pval, signed, unit_html, value_html
from selfcal.io.atomic import atomic_write_text

__all__ = ["CSS", "allan_table", "figure_to_data_uri", "format_estimate", "num", "plot_allan", "png_to_data_uri",
           "pval", "render_report", "write_report"]

# pages embed the style as <style>{CSS}</style>, and the block has always opened on a line of its own
CSS = "\n" + resources.files(__name__).joinpath("templates", "style.css").read_text(encoding="utf-8")

# Autoescape stays off: text is escaped in the templates with |esc, which is html.escape (quotes as &quot; and
# &#x27;, as the report has always written them; Jinja's own escape writes &#34; and &#39;), and the number
# filters return HTML.  trim_blocks and lstrip_blocks make a block tag's line vanish; every other character of
# a template, line breaks included, is output (a "-" inside a tag drops the white space on its side).
_ENV = jinja2.Environment(loader=jinja2.PackageLoader(__name__, "templates"), autoescape=False,
                          trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True,
                          undefined=jinja2.StrictUndefined)
_ENV.filters.update(esc=html.escape, num=num, pval=pval, p_class=p_class, signed=signed, unit=unit_html,
                    value=value_html)
_ENV.tests["finite"] = finite


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
    return _ENV.get_template("page.html").render(css=CSS, **sections.page(result, extras))
