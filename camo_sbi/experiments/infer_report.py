"""The pages of `camo-sbi infer`: report.html of one recording (`write_infer_report`: the model
check, the limits, the settings, observed vs posterior-predictive reaches), the limits figure
and wide table (`limits_html`, also each subject's section of a folder's report), and the
reproduction check of every posterior (`model_checks`, `camo_sbi.diagnostics.misspecification`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from camo_sbi.experiments.infer_limits import FALLBACK_MARK, WIDE_LIMITS_KEY, wide_limits

# only light modules at import time (numpy, torch and matplotlib are imported by the functions that use them)
if TYPE_CHECKING:
    import numpy as np
    import torch

    from camo_sbi.diagnostics.pages import Markup

__all__ = ["MAX_REPORT_REACHES", "MODEL_CHECK_STREAM", "PPC_DRAWS", "limits_html", "method_title", "model_checks",
           "reach_figure", "write_infer_report"]

PPC_DRAWS = 50
"""Posterior-predictive draws per method in each reach's figure."""
MAX_REPORT_REACHES = 12
"""Reaches drawn in the report (the rest are counted)."""


def limits_html(table, sim) -> Markup:
    """The limits figure (model range, estimates, 90% intervals, "not exercised") and the wide table."""
    import numpy as np

    from camo_sbi.diagnostics.figures import plot_limits
    from camo_sbi.diagnostics.pages import join, part
    from camo_sbi.diagnostics.report import figure_html, table_html

    types = getattr(getattr(sim, "spec", None), "joint_types", ("revolute",) * sim.n_joints)
    b = np.degrees(sim.bounds.double().numpy())
    ranges = {j: (float(b[i, 0]), float(b[i, 1])) for i, j in enumerate(sim.joint_names) if types[i] == "revolute"}
    parts = []
    if ranges:
        parts.append(figure_html(plot_limits(table, ranges),
                                 "Inferred joint limits [deg]: the model's range (grey), each method's estimate "
                                 "(marker) and 90% interval (line); hollow markers: bounds no reach exercised (not "
                                 "an impairment: the data say nothing about them)", alt="limits figure"))
    parts.append(part("meta", WIDE_LIMITS_KEY) + part("wide", table_html(wide_limits(table), index=True)))
    return join(parts)


def _shown_limits(table):
    """The limits table as a person reads it: degrees only (radians stay in limits.csv),
    unless a prismatic joint (metres, no degree column) needs ``estimate_rad``."""
    if table["estimate_deg"].notna().all():
        return table.drop(columns=["estimate_rad"])
    return table


def _ee_of(traj_ee: torch.Tensor, length: torch.Tensor, b: int) -> np.ndarray:
    import torch

    return traj_ee[b, : int(length[b])].to(torch.float64).numpy()


def method_title(name: str, status: str) -> str:
    """A panel title: the method's name, with `FALLBACK_MARK` when its status is not "ok" (the
    status itself, often a long sentence, goes into the caption, never into a title)."""
    return name if status == "ok" else f"{name} {FALLBACK_MARK}"


def reach_figure(sim, o, results: dict, draws: dict):
    """One reach: per method (columns) the end-effector path from above (top) and the distance
    to the goal per step (bottom): observed, the estimate's prediction, the posterior draws."""
    import numpy as np
    import torch
    from matplotlib.figure import Figure

    from camo_sbi.diagnostics.style import DOUBLE_COLUMN
    from camo_sbi.task import contain

    methods = list(results)
    seen = (o.ee if o.ee is not None else sim.forward_kinematics(o.q)).to(torch.float64).numpy()
    fig = Figure(figsize=(max(DOUBLE_COLUMN, 1.75 * len(methods)), 4.4), constrained_layout=True)
    axes = fig.subplots(2, len(methods), squeeze=False)
    for c, m in enumerate(methods):
        # float32, as CAMO's candidates: a new chain's float64 kernel is not compiled for a figure
        th = contain(draws[m], o.start).to(torch.float32)
        pred = sim.simulate(th, o.goal, o.start)
        est = sim.simulate(contain(torch.as_tensor(results[m].estimate), o.start).to(torch.float32), o.goal,
                           o.start)
        top, side = axes[0, c], axes[1, c]
        for b in range(th.shape[0]):
            e = _ee_of(pred.ee, pred.length, b)
            top.plot(e[:, 0], e[:, 1], color="C0", alpha=0.15, lw=0.8)
            side.plot(np.arange(e.shape[0]), np.linalg.norm(e - o.goal.numpy(), axis=1), color="C0",
                      alpha=0.15, lw=0.8)
        e = _ee_of(est.ee, est.length, 0)
        top.plot(e[:, 0], e[:, 1], color="C3", ls="--", lw=1.2, label="estimate")
        side.plot(np.arange(e.shape[0]), np.linalg.norm(e - o.goal.numpy(), axis=1), color="C3", ls="--",
                  lw=1.2)
        top.plot(seen[:, 0], seen[:, 1], color="k", lw=1.8, label="observed")
        side.plot(np.arange(seen.shape[0]), np.linalg.norm(seen - o.goal.numpy(), axis=1), color="k", lw=1.8)
        top.plot(*o.goal.numpy()[:2], marker="*", color="k", ms=10, ls="none")
        top.set_title(method_title(m, results[m].status))
        top.set_xlabel("x [m]")
        top.set_ylabel("y [m]")
        top.set_aspect("equal", adjustable="datalim")
        side.set_xlabel("controller step")
        side.set_ylabel("distance to goal [m]")
        if c == 0:
            top.legend()
    return fig


MODEL_CHECK_STREAM = 33
"""Seed stream of the reproduction check (`derive_seed(seed, MODEL_CHECK_STREAM)`)."""


def model_checks(task, results: dict, seed: int) -> dict:
    """{method: `ReproductionCheck`}: does each posterior reproduce each observed reach (issue 33)?"""
    from camo_sbi._validation import derive_seed
    from camo_sbi.diagnostics.misspecification import check_reproduction

    return {name: check_reproduction(task, res, seed=derive_seed(seed, MODEL_CHECK_STREAM))
            for name, res in results.items()}


def _check_html(checks: dict):
    """The report's opening section: the warnings of the check, then its per-reach table."""
    import pandas as pd

    from camo_sbi.diagnostics.misspecification import reach_rows, verdict_lines
    from camo_sbi.diagnostics.pages import join, part
    from camo_sbi.diagnostics.report import table_html

    lines = [w for c in checks.values() for w in verdict_lines(c)]
    head = part("items", lines) if lines else part(
        "meta", "every posterior checked reproduces every reach (Holm-adjusted p >= 0.05)")
    return join([head, part("wide", table_html(pd.DataFrame(reach_rows(checks))))])


def write_infer_report(out: Path, task, results: dict, notes: list[str], table, settings: dict, seed: int,
            formats=None, speed: dict | None = None, checks: dict | None = None) -> Path:
    """report.html: the model check (``checks``: does each posterior reproduce each reach?), the
    limits table (degrees) and, per reach, observed vs posterior-predictive paths (``speed``: the
    hand speed with the reach cuts); with ``formats`` (``--figure-format``) the figures also as
    files in ``out/report_figures``."""
    from camo_sbi.diagnostics.report import figure_files
    from camo_sbi.diagnostics.style import paper_style

    with paper_style(), figure_files(out / "report_figures", formats):
        return _report_page(out, task, results, notes, table, settings, seed, speed, checks)


def _report_page(out: Path, task, results: dict, notes: list[str], table, settings: dict, seed: int,
                 speed: dict | None = None, checks: dict | None = None) -> Path:
    import pandas as pd
    import torch

    from camo_sbi.diagnostics.pages import join, part
    from camo_sbi.diagnostics.report import figure_html, table_html, write_page

    sim = task.simulator
    obs = task.observations[:MAX_REPORT_REACHES]
    methods = list(results)
    reach_html = []
    # per method: PPC_DRAWS systematic posterior draws (deterministic), simulated once per reach
    draws = {m: torch.as_tensor(r.systematic(PPC_DRAWS if r.samples.shape[0] > 1 else 1), dtype=torch.float64)
             for m, r in results.items()}
    for i, o in enumerate(tqdm(obs, desc="report", unit="reach")):
        fig = reach_figure(sim, o, results, draws)
        fallback = [m for m in methods if results[m].status != "ok"]
        reach_html.append(figure_html(
            fig, f"reach {i}: observed (black), the estimate's prediction (red dashed) and "
                 f"{PPC_DRAWS} posterior-predictive draws per method (blue; point methods: one); "
                 f"top: end-effector path seen from above, bottom: distance to the goal per step"
                 + (f"; {FALLBACK_MARK}: fell back or failed ({'; '.join(f'{m}: {results[m].status}' for m in fallback)})"
                    if fallback else ""),
            alt=f"reach {i}"))
    more = len(task.observations) - len(obs)
    if more > 0:
        reach_html.append(part("meta", f"{more} more reaches not shown"))
    settings_html = part("wide", table_html(pd.DataFrame([{"setting": k, "value": str(v)}
                                                          for k, v in settings.items()])))
    sections = ([("model-check", "Does the model reproduce the recording?", _check_html(checks))] if checks else []) + [
        ("limits", "Estimated limits", limits_html(table, sim)),
        ("settings", "Settings", settings_html + (part("items", notes) if notes else "")),
        ("limits-table", "All columns of limits.csv",
         part("meta", "degrees (limits.csv also holds radians, estimate_rad)")
         + part("wide", table_html(_shown_limits(table), float_format="{:.4g}"))),
        ("reaches", "Observed vs posterior-predictive reaches", join(reach_html)),
    ]
    if speed is not None:
        from camo_sbi.diagnostics.figures import plot_speed

        sections.insert(2, ("reaches-found", "Reaches found", figure_html(
            plot_speed(speed["time"], speed["speed"], speed["cuts"]),
            f"hand speed ({speed['source']}) and the {len(speed['cuts'])} reaches found (shaded, numbered as in "
            f"reaches.csv); rule: {speed['rule']}", alt="hand speed with the cuts")))
    return write_page(out / "report.html", f"camo_sbi infer: {settings['observations']}", sections,
                      meta=f"model {task.name}, {len(task.observations)} reaches, seed {seed}")
