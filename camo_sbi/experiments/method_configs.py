"""The config a grid cell runs a method with, and ``--config METHOD=JSON``, in one place.

`method_config` serves every command (compare, calibrate, robustness, infer and ``reproduce
panda``): each passes what it decides (the per-task budget whose declared defaults apply, the
observation space, a work directory, the trained estimator file, a setting's CAMO options, the
user's overrides) and gets the dict the method runs with, so the rule "which config field comes
from where" lives here rather than in each command.
`parse_configs` reads the repeatable ``--config`` option (compare, calibrate, infer) and
validates it against each method's config class.
"""

from __future__ import annotations

from camo_sbi._files import parse_json

__all__ = ["method_config", "parse_configs"]


def method_config(method: str, *, budget: int | None = None, space: str | None = None, workdir=None,
                  estimator_path: str | None = None, camo: dict | None = None, overrides: dict | None = None) -> dict:
    """The config dict a grid cell runs ``method`` with, built in this order:

    * ``budget``: the values the method declares for this per-task budget
      (`registry.budget_defaults`); None: none (compare's cells never applied them);
    * ``space``: for a method that chooses its observation space and whose variant does not fix it;
    * ``workdir``: for a method that writes artefacts (`Capabilities.workdir`), as a str;
    * ``estimator_path``: for an amortized method (the trained estimator file);
    * ``camo``: a setting's CAMO options (``reproduce panda``), for a method that runs on CAMO's
      config class (the CAMO variants and camo-touched); an ``epsilon`` given per observation
      space (``{"joint": ..., "cartesian": ...}``) takes the method's space, and the sequential
      JS proposals (camo-seq-cs) also get the joint one as ``js_epsilon``;
    * ``overrides``: the user's ``--config`` values, last. An ``estimator_path`` among them that
      differs from ``estimator_path`` is refused (ValueError): which of the two a cell used
      differed between commands.

    Arguments left None add nothing.
    """
    from camo_sbi.inference.registry import budget_defaults, get_method

    spec = get_method(method)
    if overrides is not None and not isinstance(overrides, dict):
        raise TypeError(f"overrides: expected a dict or None, got {type(overrides).__name__}")
    cfg: dict = {} if budget is None else budget_defaults(method, budget)
    if space is not None and len(spec.capabilities.spaces) > 1 and "space" not in spec.defaults:
        cfg["space"] = space
    if workdir is not None and spec.capabilities.workdir:
        cfg["workdir"] = str(workdir)
    if estimator_path is not None and spec.capabilities.amortized:
        cfg["estimator_path"] = str(estimator_path)
        other = (overrides or {}).get("estimator_path", cfg["estimator_path"])
        if str(other) != cfg["estimator_path"]:
            raise ValueError(f"overrides: {method}: estimator_path {other!r} differs from the estimator file "
                             f"{cfg['estimator_path']!r} (--amortized); give one of them")
    if camo is not None and spec.load().config is get_method("camo").load().config:
        cfg.update(camo)
        if isinstance(cfg.get("epsilon"), dict):
            per_space = cfg["epsilon"]
            cfg["epsilon"] = per_space[spec.defaults.get("space", cfg.get("space", "joint"))]
            if spec.defaults.get("proposal") == "sequential-js":  # the JS chain of camo-seq-cs
                cfg["js_epsilon"] = per_space["joint"]
    return {**cfg, **(overrides or {})}


def parse_configs(entries, methods: list[str]) -> dict[str, dict]:
    """``--config METHOD=JSON`` (repeatable) -> {method: overrides}, validated against the config class."""
    from camo_sbi.inference.registry import make_config

    out: dict[str, dict] = {}
    for entry in entries or []:
        name, sep, text = str(entry).partition("=")
        name = name.strip()
        if not sep:
            raise ValueError(f"--config: expected METHOD=JSON, got {entry!r}")
        if name not in methods:
            raise ValueError(f"--config: method {name!r} is not in --methods ({', '.join(methods)})")
        cfg = parse_json(text, f"--config: {name}")
        if not isinstance(cfg, dict):
            raise ValueError(f"--config: {name}: expected a JSON object, got {text!r}")
        out[name] = {**out.get(name, {}), **cfg}
    for name, cfg in out.items():
        try:
            make_config(name, dict(cfg))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"--config: {name}: {exc}") from exc
    return out
