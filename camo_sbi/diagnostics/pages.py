"""HTML pages from the jinja2 templates in ``diagnostics/templates`` (the only jinja2 import).

Why templates: report.html and infer's pages were assembled from f-strings with an
``html.escape`` call wherever someone remembered one; a joint, method or model name, a path, a
caption or an error message that reached a page unescaped would have been markup. Here one
`jinja2.Environment` (built once, autoescaping on, `StrictUndefined`) renders fixed template
files, and every value reaches them as a variable, so every string is escaped unless it is a
`Markup` fragment these templates rendered themselves. The templates:

    page.html.j2     the page layout: title, input digest, style, navigation, sections
    parts.html.j2    the repeated pieces, as macros: section, table, figure with caption,
                     note / error box, meta line, heading, details, list, flex row of tables

`part` calls one macro of parts.html.j2 and returns its `Markup`; `join` concatenates fragments
(a plain ``str`` among them is escaped, never trusted); `table_parts` turns a DataFrame into the
cells the ``table`` macro lays out (pandas' own cell text: its float format, "–" for missing,
a MultiIndex's repeated labels spanning rows). `template_bytes` is what a report's input
digest hashes, so a changed template rebuilds the reports.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from importlib import resources

import jinja2
import numpy as np
import pandas as pd
from markupsafe import Markup

__all__ = ["Markup", "join", "page", "part", "table_parts", "template_bytes", "TEMPLATES"]
TEMPLATES = ("page.html.j2", "parts.html.j2")
_NA = "–"


@functools.cache
def _environment() -> jinja2.Environment:
    """The one environment: templates from the package's ``templates`` folder, every value
    autoescaped (also in templates whose names ``select_autoescape`` would not know), an
    undefined variable an error rather than an empty string."""
    return jinja2.Environment(
        loader=jinja2.PackageLoader("camo_sbi.diagnostics", "templates"),
        autoescape=jinja2.select_autoescape(enabled_extensions=("html", "html.j2"), default_for_string=True,
                                            default=True),
        undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)


@functools.cache
def _parts():
    return _environment().get_template("parts.html.j2").module


def part(name: str, *args, **kwargs) -> Markup:
    """The macro ``name`` of parts.html.j2 called with these values (each escaped by the macro)."""
    macro = getattr(_parts(), name, None)
    if macro is None:
        raise ValueError(f"name: parts.html.j2 has no macro {name!r}")
    return Markup(macro(*args, **kwargs))


def join(fragments: Iterable) -> Markup:
    """Fragments one after another: `Markup` as it is, anything else as escaped text."""
    return Markup("").join(fragments)


def page(**values) -> str:
    """page.html.j2 rendered with ``values`` (title, digest_meta, digest, meta, sections)."""
    return _environment().get_template("page.html.j2").render(**values)


def template_bytes() -> bytes:
    """Every template's name and bytes, for the report's input digest."""
    folder = resources.files("camo_sbi.diagnostics") / "templates"
    return b"".join(n.encode() + b"\0" + (folder / n).read_bytes() for n in TEMPLATES)


def _cell_text(v, float_format: str) -> str:
    """A cell as pandas' ``to_html`` writes it: missing -> "–", floats through ``float_format``."""
    if v is None or v is pd.NaT or (isinstance(v, (float, np.floating)) and np.isnan(v)):
        return _NA
    if isinstance(v, (float, np.floating)):
        return float_format.format(v)
    return str(v)


def table_parts(df: pd.DataFrame, *, index: bool, float_format: str | None = None) -> dict:
    """The header rows and body rows of ``df`` for the ``table`` macro.

    Each cell is ``{"text", "header", "rowspan"}``; the layout follows pandas' ``to_html``:
    with ``index``, one header cell per index level (their names in a second header row when
    any is named) and the index labels as row headers, a MultiIndex's repeated outer labels as
    one cell spanning their rows.
    """
    if not isinstance(df, pd.DataFrame):
        raise TypeError(f"df: expected a pandas DataFrame, got {type(df).__name__}")
    fmt = float_format or "{}"

    def cell(text, header=False, rowspan=1):
        return {"text": text, "header": header, "rowspan": rowspan}

    names = [n for n in df.index.names] if index else []
    top = ([cell("" if df.columns.name is None or i < len(names) - 1 else str(df.columns.name), True)
            for i in range(len(names))] + [cell(str(c), True) for c in df.columns])
    head = [top]
    if index and any(n is not None for n in names):
        head.append([cell("" if n is None else str(n), True) for n in names] + [cell("", True) for _ in df.columns])
    labels = [t if isinstance(t, tuple) else (t,) for t in df.index] if index else []
    body = []
    for r, values in enumerate(df.itertuples(index=False, name=None)):
        row = []
        for level in range(len(names)):
            prefix = labels[r][: level + 1]
            if level < len(names) - 1:
                if r > 0 and labels[r - 1][: level + 1] == prefix:
                    continue  # inside the span of the label above
                span = 1
                while r + span < len(labels) and labels[r + span][: level + 1] == prefix:
                    span += 1
                row.append(cell(_cell_text(prefix[-1], fmt), True, span))
            else:
                row.append(cell(_cell_text(prefix[-1], fmt), True))
        row += [cell(_cell_text(v, fmt)) for v in values]
        body.append(row)
    return {"head": head, "body": body}
