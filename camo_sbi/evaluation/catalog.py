"""Every metric camo_sbi records, as data: one ordered list (`METRICS`) of `Metric` records.

Why a list: the scorer (`camo_sbi.evaluation.evaluate.evaluate_result`) computes each metric
that has a ``score``, the tables list the metrics in this order, the figures plot the
``headline`` ones, the labels and units come from here, and the claims name what they test
by ``claims`` tags; so a metric added here reaches every table and figure without another
edit. Metrics without a ``score`` are recorded by the command that knows them (the task's
binding counts, the block-stacking allocation scores, the estimated body scale).

Why a module of its own rather than `camo_sbi.evaluation.metrics`: the report, the style
helpers and the claims read the list where torch must not be imported (a re-run of a
finished grid imports neither torch nor matplotlib), and the metrics module is torch code.
The score functions only read the `camo_sbi.evaluation.evaluate.Scoring` they are given
(which computes with the metrics module), so importing this module costs nothing.

A score function takes the `camo_sbi.evaluation.evaluate.Scoring` of one result and returns
what ``aggregate`` reduces ("mean" or "sum" over the array's elements: the test reaches, the
posterior draws' reaches, the free bounds; "value": already one number), or None when the
metric does not apply (no held-out reaches, no truth, no posterior, an empty group). A
``per_joint`` metric is a family: its ``name`` holds ``{joint}`` and its score returns a
mapping from joint name to what ``aggregate`` reduces, one row per joint.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

__all__ = ["AGGREGATES", "METRICS", "Metric", "find", "get", "headline", "ordered", "tagged"]

AGGREGATES = ("mean", "sum", "value")


@dataclass(frozen=True)
class Metric:
    """One metric: its results.csv name, how it reads, how it is scored and shown.

    ``label``: words without the unit; ``unit``: the unit the files store it in ("rad" is
    shown in degrees, `display_unit`); ``aggregate``: how the score is reduced to one
    value (module docstring); ``headline``: plotted in the figures; ``group``: what it
    measures ("prediction", "reachability", "posterior_predictive", "limits", "interval",
    "reference", "cost", "design", "task", "allocation", "model_check"); ``lower_is_better``: False for scores and shares where
    more is better; ``reference``: a value drawn as a line in figures (a nominal level),
    or None; ``claims``: tags of the claims that test it (`camo_sbi.evaluation.claims`);
    ``score``: the scoring function, None for a metric a command records itself.
    """

    name: str
    label: str
    unit: str
    aggregate: str
    headline: bool = False
    group: str = ""
    per_joint: bool = False
    lower_is_better: bool = True
    reference: float | None = None
    claims: tuple[str, ...] = ()
    score: Callable[[Any], Any] | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"name: expected a non-empty str, got {self.name!r}")
        if self.per_joint != ("{joint}" in self.name):
            raise ValueError(f"name: a per-joint metric's name holds '{{joint}}' and only it, got {self.name!r}")
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"aggregate: expected one of {AGGREGATES}, got {self.aggregate!r}")
        if self.score is not None and not callable(self.score):
            raise TypeError(f"score: expected a callable or None, got {type(self.score).__name__}")

    @property
    def prefix(self) -> str:
        """The start every row name of this metric shares (the name itself unless per-joint)."""
        return self.name.split("{joint}")[0]

    def row(self, joint: str | None = None) -> str:
        """The results.csv name of a row: the name, or for a per-joint metric the joint's."""
        return self.name.format(joint=joint) if self.per_joint else self.name

    def matches(self, row_name: str) -> bool:
        """Whether a results.csv metric name is this metric's (one of its joints' for a family)."""
        row_name = str(row_name)
        return row_name.startswith(self.prefix) and len(row_name) > len(self.prefix) if self.per_joint \
            else row_name == self.name

    def reduce(self, value):
        """A score's value reduced by ``aggregate`` to the number a row holds."""
        if self.aggregate == "mean":
            return float(value.mean())
        if self.aggregate == "sum":
            return float(value.sum())
        return value

    @property
    def display_unit(self) -> str:
        """The unit a person reads: angles stored in radians are shown in degrees."""
        return "deg" if self.unit == "rad" else self.unit

    def display_label(self, joint: str | None = None) -> str:
        """The label with the displayed unit, e.g. "Cartesian error per point [mm]"."""
        label = self.label.format(joint=joint) if self.per_joint else self.label
        return f"{label} [{self.display_unit}]" if self.display_unit else label


# --------------------------------------------------------------------------- score functions
# each reads the Scoring (evaluate.py) of one result, which computes with the metrics module


def _trajectory(fn_name: str):
    def score(s):
        return s.trajectory_error(fn_name)

    score.__name__ = f"score_{fn_name}"
    return score


def _field(attr: str, key: str):
    def score(s):
        d = getattr(s, attr)
        return None if d is None else d.get(key)

    score.__name__ = f"score_{key}"
    return score


def _ppc_expected(s):
    return s.ppc_expected_error


def _ppc_mean_path(s):
    return s.ppc_mean_path_error


def _result_attr(attr: str):
    def score(s):
        return getattr(s.result, attr)

    score.__name__ = f"score_{attr}"
    return score


def _result_extra(key: str):
    def score(s):
        return s.result.extras.get(key)

    score.__name__ = f"score_{key}"
    return score


def _coverage(s):
    return s.coverage90


def _per_joint_limit_error(s):
    return s.joint_limit_errors


_M = Metric

METRICS: list[Metric] = [
    # prediction: the estimate's predicted held-out reaches against the true ones
    _M("cartesian_error_mm", "Cartesian error per point", "mm", "mean", headline=True, group="prediction",
       claims=("primary", "fig2", "informative"), score=_trajectory("cartesian_error_mm")),
    _M("joint_error_deg", "joint error per joint and point", "deg", "mean", headline=True, group="prediction",
       claims=("fig3",), score=_trajectory("joint_error_deg")),
    _M("eq2_cartesian", "Eq. 2 (Cartesian), Σ goals", "m", "sum", group="prediction",
       score=_trajectory("eq2_cartesian")),
    _M("eq2_joint", "Eq. 2 (joint), Σ goals", "rad", "sum", group="prediction", score=_trajectory("eq2_joint")),
    _M("reference_cartesian", "authors' metric (Cart.), Σ goals", "m", "sum", headline=True, group="prediction",
       claims=("fig2",), score=_trajectory("reference_cartesian")),
    _M("reference_joint", "authors' metric (joint), Σ goals", "rad", "sum", headline=True, group="prediction",
       claims=("fig3",), score=_trajectory("reference_joint")),
    # reachability of the held-out goals (informative setting)
    _M("reachability_precision", "reachability precision", "", "value", group="reachability",
       lower_is_better=False, score=_field("reachability", "reachability_precision")),
    _M("reachability_recall", "reachability recall", "", "value", group="reachability", lower_is_better=False,
       score=_field("reachability", "reachability_recall")),
    _M("reachability_f1", "reachability F1", "", "value", headline=True, group="reachability",
       lower_is_better=False, score=_field("reachability", "reachability_f1")),
    _M("reachability_accuracy", "reachability accuracy", "", "value", group="reachability",
       lower_is_better=False, score=_field("reachability", "reachability_accuracy")),
    # posterior-predictive (posteriors only)
    _M("ppc_cartesian_error_mm", "posterior-predictive Cartesian error", "mm", "mean", headline=True,
       group="posterior_predictive", score=_ppc_expected),
    _M("pp_mean_cartesian_error_mm", "error of the posterior-predictive mean path", "mm", "mean",
       group="posterior_predictive", score=_ppc_mean_path),
    # limits (synthetic subjects: the truth is known)
    _M("limit_error_deg", "mean |limit error|, free limits", "deg", "mean", headline=True, group="limits",
       score=_field("limit_groups", "limit_error_deg")),
    _M("limit_error_binding_deg", "mean |limit error|, binding limits", "deg", "mean", headline=True,
       group="limits", claims=("informative", "limits"), score=_field("limit_groups", "limit_error_binding_deg")),
    _M("limit_error_free_deg", "mean |limit error|, non-binding limits", "deg", "mean", headline=True,
       group="limits", claims=("limits",), score=_field("limit_groups", "limit_error_free_deg")),
    _M("limit_error_deg_{joint}", "|limit error| of {joint}", "deg", "mean", group="limits", per_joint=True,
       score=_per_joint_limit_error),
    _M("coverage90", "coverage of the 90% interval", "", "value", headline=True, group="interval",
       lower_is_better=False, reference=0.9, score=_coverage),
    # against a reference posterior (compare --reference; recorded by the command, sbibm's metrics)
    _M("c2st", "C2ST accuracy against the reference posterior", "", "value", group="reference", reference=0.5),
    _M("mmd", "squared MMD to the reference posterior", "", "value", group="reference", reference=0.0),
    _M("posterior_distinct_draws", "distinct posterior draws compared with the reference", "", "value",
       group="reference", lower_is_better=False),
    _M("reference_check_c2st", "C2ST between the reference's two runs", "", "value", group="reference",
       reference=0.5),
    # cost
    _M("n_simulations", "simulations used", "", "value", group="cost", score=_result_attr("n_simulations")),
    _M("wall_time", "wall time", "s", "value", group="cost", score=_result_attr("wall_time")),
    _M("compile_time", "numba compile time", "s", "value", group="cost", score=_result_attr("compile_time")),
    _M("import_time", "import time (sbi, pyabc)", "s", "value", group="cost", score=_result_attr("import_time")),
    _M("training_simulations", "training simulations (amortized, once)", "", "value", group="cost",
       score=_result_extra("training_simulations")),
    _M("training_time", "training time (amortized, once)", "s", "value", group="cost",
       score=_result_extra("training_time")),
    # recorded by reproduce panda --design active: what choosing the observed goals cost
    _M("design_simulations", "design criterion's simulations", "", "value", group="design"),
    _M("design_method_simulations", "design method's simulations", "", "value", group="design"),
    _M("design_fallbacks", "design steps that fell back to a random goal", "", "value", group="design"),
    _M("design_wall_time", "design wall time", "s", "value", group="design"),
    # recorded by the commands: the task's binding counts, the model's estimated body scale
    _M("binding_test_fraction", "share of held-out reaches the limits bind", "", "value", group="task"),
    _M("binding_test_reaches", "held-out reaches the limits bind", "", "value", group="task"),
    _M("binding_train_fraction", "share of observed reaches the limits bind", "", "value", group="task"),
    _M("binding_train_reaches", "observed reaches the limits bind", "", "value", group="task"),
    _M("binding_test_bound_min_fraction", "least share of held-out reaches one bound moves", "", "value",
       group="task"),
    _M("body_scale", "estimated body scale", "", "value", group="task"),
    # the reproduction check of the final posterior (camo_sbi.diagnostics.misspecification, issue 33)
    _M("model_check_p", "model check p-value (Holm over reaches)", "", "value", group="model_check",
       lower_is_better=False),
    _M("model_check_flagged", "recording flagged: the model does not reproduce it", "", "value",
       group="model_check"),
    # block stacking (reproduce hrc): the allocation of the test blocks
    _M("precision", "precision", "", "value", group="allocation", lower_is_better=False, claims=("fig5",)),
    _M("recall", "recall", "", "value", group="allocation", lower_is_better=False, claims=("fig5",)),
    _M("f1", "F1", "", "value", headline=True, group="allocation", lower_is_better=False, claims=("fig5",)),
    _M("accuracy", "accuracy", "", "value", group="allocation", lower_is_better=False),
    _M("person_fraction", "share of blocks the person can do", "", "value", group="task"),
]
"""Every metric in table order (module docstring). Read it at call time (``catalog.METRICS``),
never copy it at import, so a metric added to it (or a test's extra one) reaches every reader."""


def find(row_name: str) -> Metric | None:
    """The metric a results.csv name belongs to (a per-joint family's for its joints' rows), or None."""
    row_name = str(row_name)
    for m in METRICS:
        if not m.per_joint and m.name == row_name:
            return m
    return next((m for m in METRICS if m.per_joint and m.matches(row_name)), None)


def get(name: str) -> Metric:
    """The metric named ``name`` (a results.csv name); ValueError naming the known ones otherwise."""
    m = find(name)
    if m is None:
        raise ValueError(f"name: unknown metric {name!r}; known: {[x.name for x in METRICS]}")
    return m


def ordered(row_names: Iterable[str]) -> list[str]:
    """Distinct results.csv metric names in table order: the catalog's, then unknown ones by name."""
    index = {id(m): i for i, m in enumerate(METRICS)}

    def key(n):
        m = find(n)
        return (index[id(m)] if m is not None else len(index), n)

    return sorted(dict.fromkeys(str(n) for n in row_names), key=key)


def headline(row_names: Iterable[str] | None = None) -> list[str]:
    """The headline metrics' names in order (per-joint families never: one panel per joint is
    a table); with ``row_names``, only those among them (a results table's metrics)."""
    names = [m.name for m in METRICS if m.headline and not m.per_joint]
    if row_names is None:
        return names
    present = set(map(str, row_names))
    return [n for n in names if n in present]


def tagged(tag: str, row_names: Iterable[str] | None = None) -> list[str]:
    """The names of the metrics whose ``claims`` hold ``tag``, in order (with ``row_names``:
    only those among them)."""
    names = [m.name for m in METRICS if tag in m.claims and not m.per_joint]
    if row_names is None:
        return names
    present = set(map(str, row_names))
    return [n for n in names if n in present]
