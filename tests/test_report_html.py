"""The HTML pages are rendered from jinja2 templates with autoescaping (issue 26).

A name a user or a file supplies (a method, subject or task in results.csv, a setting, a
title, a URDF joint name, a recording's file name) reaches report.html as escaped text, never
as markup; the templates ship with the package; a plain string handed to `write_page` is text;
a DataFrame's table says what pandas' ``to_html`` said; a changed template rebuilds a report.
"""

from __future__ import annotations

import html
import json
import re
import urllib.parse
from html.parser import HTMLParser
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from camo_sbi.diagnostics import pages, report
from camo_sbi.experiments.cli import main

DATA = Path(__file__).parent / "data"
SCRIPT = "<script>alert(1)</script>"
IMG = "<img src=x onerror=alert(2)>"  # also a valid file name (no slash)


def _no_markup_from_users(text: str) -> None:
    assert SCRIPT not in text and IMG not in text
    assert not re.search(r"<script\b|onerror=", text.replace("onerror=alert(2)&gt;", ""), flags=re.I)


def _visible(markup: str) -> str:
    """The page's text as a reader sees it, whitespace normalised."""
    class Text(HTMLParser):
        def __init__(self):
            super().__init__(convert_charrefs=True)
            self.parts = []

        def handle_data(self, data):
            self.parts.append(data)

        def handle_starttag(self, tag, attrs):
            self.parts.append(" ")

    t = Text()
    t.feed(markup)
    return " ".join("".join(t.parts).split())


def test_templates_ship_as_package_data():
    folder = resources.files("camo_sbi.diagnostics") / "templates"
    shipped = sorted(p.name for p in folder.iterdir() if p.name.endswith(".j2"))
    assert shipped == sorted(pages.TEMPLATES)  # every template is in the report's digest
    assert all((folder / n).read_bytes() for n in pages.TEMPLATES)


def test_hostile_names_in_a_run_directory_are_escaped(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    rows = [{"task": SCRIPT, "subject": IMG, "method": m, "budget": 100, "seed": s, "n_tasks": 2,
             "metric": "limit_rmse", "value": 0.1 + s, "status": "ok" if m == "naive" else SCRIPT}
            for m in (SCRIPT, "naive") for s in range(2)]
    rows += [{**r, "task": "t2"} for r in rows]  # two groups: headings name the task and subject
    pd.DataFrame(rows).to_csv(run / "results.csv", index=False)
    (run / "config.json").write_text(json.dumps({SCRIPT: IMG, "methods": [SCRIPT]}))
    text = report.write_report(run, tmp_path / "report.html", title=f"run {SCRIPT}").read_text(encoding="utf-8")
    _no_markup_from_users(text)
    escaped = html.escape(SCRIPT, quote=False)
    assert f"<title>run {escaped}</title>" in text and f"<h1>run {escaped}</h1>" in text
    assert f"<td>{escaped} †</td>" in text  # the method's row, marked for its non-ok status
    assert f"<h3>task {escaped}, subject {html.escape(IMG, quote=False)}</h3>" in text
    assert f"<td>{escaped}</td>" in text  # the setting's key in the settings table
    seen = _visible(text)
    assert f"run {SCRIPT}" in seen and f"{SCRIPT}: {SCRIPT}" in seen  # the reader sees the name as written


def test_hostile_joint_and_file_names_are_escaped_in_infer_reports(tmp_path):
    """A URDF joint named like a script tag, and a recording file named like an img tag."""
    urdf = tmp_path / "arm.urdf"
    urdf.write_text((DATA / "arm7.urdf").read_text().replace('joint name="elbow"',
                                                            f'joint name="{html.escape(SCRIPT)}"'))
    limits = json.loads((DATA / "arm7_limits.json").read_text())
    limits[SCRIPT] = limits.pop("elbow")
    (tmp_path / "limits.json").write_text(json.dumps(limits))
    model = ["--urdf", str(urdf), "--ee", "tool", "--start", "0,0.4,0,-1.1,0,0.7,0"]
    folder = tmp_path / "recs"
    folder.mkdir()
    assert main(["simulate-observations", *model, "--limits", str(tmp_path / "limits.json"), "--reaches", "2",
                 "--seed", "2", "--out", str(folder / f"{IMG}.csv")]) == 0
    out = tmp_path / "infer"
    assert main(["infer", "--observations", str(folder), *model, "--methods", "naive,nominal", "--budget", "20",
                 "--seed", "0", "--out", str(out)]) == 0
    summary = (out / "report.html").read_text(encoding="utf-8")
    subject = (out / "subjects" / IMG / "report.html").read_text(encoding="utf-8")
    for text in (summary, subject):
        _no_markup_from_users(text)
        assert f"<th>{html.escape(SCRIPT, quote=False)}</th>" in text  # the joint's row of the limits table
        assert SCRIPT in _visible(text)
    assert f"<h2>Subject {html.escape(IMG, quote=False)}</h2>" in summary
    link = re.search(r'<a href="([^"]*)">its report</a>', summary).group(1)
    assert "<" not in link and (out / urllib.parse.unquote(link)).is_file()  # a working relative link


def test_write_page_shows_a_plain_string_body_as_text(tmp_path):
    out = report.write_page(tmp_path / "p.html", "t", [("s", "heading <b>", "<b>bold?</b>")], meta=SCRIPT)
    text = out.read_text(encoding="utf-8")
    assert "&lt;b&gt;bold?&lt;/b&gt;" in text and "<b>" not in text
    _no_markup_from_users(text)
    with pytest.raises(TypeError, match="^title: "):
        report.write_page(tmp_path / "p.html", 3, [])
    with pytest.raises(ValueError, match="^digest: "):
        report.write_page(tmp_path / "p.html", "t", [], digest='"><script>')
    with pytest.raises(ValueError, match="^name: "):
        pages.part("no_such_macro")


def test_a_table_says_what_pandas_to_html_said():
    frames = [
        pd.DataFrame({"a": [1.23456, np.nan, 3.0], "b": ["x", None, "<z>"], "c": [1, 2, 3],
                      "d": [0.5, "–", 2.123456], "e": [True, False, True]},
                     index=pd.MultiIndex.from_tuples([("j1", "lo"), ("j1", "hi"), ("j2", "lo")],
                                                     names=["joint", "bound"])),
        pd.DataFrame({"m": ["a", "b"], "f": [1e-7, 123456.7]}, index=pd.Index(["x", "y"], name="joint")),
        pd.DataFrame({"m": ["a", "b"], "f": [np.float32(1.5), 2]}, index=["x", "y"]),
    ]
    for df in frames:
        for index in (True, False):
            ours = report.table_html(df, index=index)
            theirs = df.to_html(index=index, escape=True, border=0, na_rep="–",
                                float_format=lambda v: f"{v:.4g}")
            assert _visible(ours) == _visible(theirs)
    with pytest.raises(TypeError, match="^df: "):
        pages.table_parts([[1]], index=False)


def test_a_changed_template_rebuilds_the_report(tmp_path, monkeypatch):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    out = report.write_report(run, tmp_path / "r.html")
    assert report.report_is_current(run, out)
    monkeypatch.setattr(report, "template_bytes", lambda: pages.template_bytes() + b"<!-- changed -->")
    assert not report.report_is_current(run, out)
