"""``--config METHOD=JSON`` for the grid commands (compare, calibrate, infer): parsed and
validated against each method's config class in one place."""

from __future__ import annotations

import json

__all__ = ["parse_configs"]


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
        try:
            cfg = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--config: {name}: invalid JSON ({exc})") from exc
        if not isinstance(cfg, dict):
            raise ValueError(f"--config: {name}: expected a JSON object, got {text!r}")
        out[name] = {**out.get(name, {}), **cfg}
    for name, cfg in out.items():
        try:
            make_config(name, dict(cfg))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"--config: {name}: {exc}") from exc
    return out
