"""`camo-sbi render-scene`: the block-stacking scene of `camo-sbi reproduce hrc` as a PNG: one random
trial (``--seed``: the layout) with the subject's true allocation (white: the person's blocks,
black: the robot's) and, unless ``--no-region``, the tabletop region the person reaches with the
true limits.

Only light modules at import time: pybullet's scene and the body model are imported by `main`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from camo_sbi.experiments.reproduce_hrc import check_subject, positive_int

__all__ = ["add_arguments", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("scene.png"), help="PNG path")
    p.add_argument("--subject", default="frozen_shoulder", help="impairment profile of the person")
    p.add_argument("--seed", type=int, default=0, help="layout seed")
    p.add_argument("--width", type=positive_int("--width"), default=800)
    p.add_argument("--height", type=positive_int("--height"), default=600)
    p.add_argument("--no-region", action="store_true", help="do not tint the reachable tabletop region")


def main(args) -> int:
    """Render one random trial with the subject's true allocation and reachable region."""
    from camo_sbi.scenarios.block_stacking import COLOURS, PERSON, ROBOT, BlockStackingScene
    from camo_sbi.simulators import human, impaired_limits

    check_subject(args.subject)
    sim = human()
    theta = impaired_limits(sim, args.subject)
    with BlockStackingScene(sim, seed=args.seed) as scene:
        labels = scene.labels(theta)
        path = scene.render(args.out, {c: PERSON if a else ROBOT for c, a in zip(COLOURS, labels, strict=True)},
                            region_theta=None if args.no_region else theta, width=args.width,
                            height=args.height,
                            title=f"{args.subject}: true allocation (white: person, black: robot)")
    print(f"scene: {path}")
    return 0
