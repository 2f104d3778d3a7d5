"""The recording options of `camo-sbi infer` and `camo-sbi simulate-observations`: the noise model
(``--noise-joint-deg``, ``--noise-ee-mm``) and how a lab's recording is read (units, a lab frame,
markers, ``--goal final``, reaches, ``--body-scale``: `add_recording_arguments`, `load_from_args`).

Only light modules at import time: the CLI builds its parser from these functions (the readers of
`camo_sbi.io` are imported by the functions that read a file).
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["MAX_REACHES", "RECORDING_SUFFIXES", "add_noise_arguments", "add_recording_arguments",
           "height_from_file", "load_from_args", "noise_from_args"]

MAX_REACHES = 2000  # --max-reaches: a light copy of camo_sbi.io.recordings.MAX_REACHES (--help needs no torch)
RECORDING_SUFFIXES = (".csv", ".npz", ".c3d", ".bvh", ".mot", ".sto")
"""The files `camo-sbi infer --observations DIR/` reads from a folder (one subject per file)."""


def noise_from_args(args):
    from camo_sbi.task import NoiseModel

    try:
        return NoiseModel(joint_deg=args.noise_joint_deg, ee_mm=args.noise_ee_mm)
    except ValueError as exc:
        flag = "--noise-joint-deg" if str(exc).startswith("joint_deg") else "--noise-ee-mm"
        raise ValueError(f"{flag}: {str(exc).split(': ', 1)[1]}") from exc


def add_noise_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--noise-joint-deg", type=float, default=0.0, help="noise sd per joint angle [deg]")
    p.add_argument("--noise-ee-mm", type=float, default=0.0, help="noise sd per end-effector coordinate [mm]")


def add_recording_arguments(p: argparse.ArgumentParser) -> None:
    """Units, frames, markers and goals of a recording (CSV, NPZ or C3D)."""
    p.add_argument("--ee-units", choices=("m", "mm"), default=None,
                   help="unit of the ee_* and goal_* columns (default m; a C3D file's POINT:UNITS is used)")
    p.add_argument("--goal", choices=("columns", "final"), default="columns",
                   help="columns: the goal_* columns; final: each reach's last end-effector position (free reaching)")
    p.add_argument("--frame", type=Path, default=None,
                   help="JSON rigid transform lab -> model base: rotation (3x3) or quaternion [w,x,y,z], "
                        "translation [m]")
    p.add_argument("--frame-from-markers", default=None, metavar="A,B,C",
                   help="estimate the frame from these C3D markers (positions in --marker-positions)")
    p.add_argument("--marker-positions", type=Path, default=None,
                   help='JSON {"marker": [x, y, z]} model-frame positions [m] for --frame-from-markers')
    p.add_argument("--ee-marker", default=None, metavar="NAME[,NAME...]",
                   help="C3D marker(s) of the end effector (several: their mean)")
    p.add_argument("--bvh-map", type=Path, default=None,
                   help="JSON mapping of a BVH file's channels to the model's joints (signs, offsets, reaches)")
    p.add_argument("--max-reaches", type=int, default=MAX_REACHES, metavar="N",
                   help="refuse a recording of more reaches (each is a task of every method; a larger one "
                        "runs with a larger N)")
    p.add_argument("--reaches", default=None, metavar="auto|events|A-B,C-D",
                   help="find the reaches in a recording with time (C3D, BVH, or a time column): auto (by hand "
                        "speed), events (the C3D file's events), or inclusive frame ranges; each reach's goal is "
                        "where it ends; DIR/reaches.csv lists them (default: the file's own reaches)")
    p.add_argument("--side", choices=("right", "left"), default=None,
                   help="the recorded arm (--markers isb mirrors a left arm onto the right-arm model; default "
                        "right) and the events' context with --reaches events")
    p.add_argument("--markers", choices=("isb",), default=None,
                   help="isb: the human model's joint angles per frame from a C3D's ISB upper-limb landmarks "
                        "(thorax, humerus, forearm, hand; angles relative to the thorax); needs --marker-map")
    p.add_argument("--marker-map", type=Path, default=None,
                   help='JSON {"IJ": "<label>", "PX": ..., "C7": ..., "T8": ..., "AC": ..., "EL": ..., "EM": ..., '
                        '"RS": ..., "US": ..., "MC2": ..., "MC5": ...}: the file\'s marker for each ISB landmark')
    p.add_argument("--out-of-range", choices=("auto", "clip", "error"), default="auto",
                   help="a joint angle beyond the model's range (more than the noise allowance): clip = clip it onto "
                        "the range with a warning per joint and mark the bound (!) in limits.csv and the report; "
                        "error = exit 2 naming it; auto = clip the angles of --markers isb (a person beyond the "
                        "model's normative range), error for every other file (a BVH map, a unit, a sign)")
    p.add_argument("--body-scale", choices=("fixed", "free"), default="fixed",
                   help="free: estimate the body's segment-length scale s in [0.85, 1.15] from the joint and "
                        "end-effector columns and infer on the scaled body")


def load_from_args(args, path, sim, noise, start):
    """`load_recording` of ``path`` with the recording flags of ``args``."""
    from camo_sbi.io.frames import load_frame, load_marker_positions
    from camo_sbi.io.recordings import load_recording

    frame = load_frame(args.frame) if args.frame is not None else None
    markers = None
    if args.frame_from_markers is not None:
        names = [m.strip() for m in str(args.frame_from_markers).split(",") if m.strip()]
        if len(names) < 3:
            raise ValueError(f"--frame-from-markers: needs three or more marker names, got {args.frame_from_markers!r}")
        if frame is not None:
            raise ValueError("--frame-from-markers: give --frame or --frame-from-markers, not both")
        if args.marker_positions is None:
            raise ValueError("--frame-from-markers: needs --marker-positions FILE.json (the markers' model-frame "
                             "positions)")
        markers = load_marker_positions(args.marker_positions, names)
    ee_markers = None
    if args.ee_marker is not None:
        ee_markers = [m.strip() for m in str(args.ee_marker).split(",") if m.strip()]
        if not ee_markers:
            raise ValueError("--ee-marker: expected one or more marker names")
    return load_recording(path, sim, degrees=args.degrees, noise=noise, start=start,
                          resample=None if args.resample == "none" else args.resample, rate=args.rate,
                          ee_units=args.ee_units, goal=args.goal, frame=frame, ee_markers=ee_markers,
                          frame_markers=markers, body_scale=getattr(args, "body_scale", "fixed"),
                          bvh_map=getattr(args, "bvh_map", None),
                          max_reaches=getattr(args, "max_reaches", MAX_REACHES), reaches=getattr(args, "reaches", None),
                          side=getattr(args, "side", None), markers=getattr(args, "markers", None),
                          marker_map=getattr(args, "marker_map", None),
                          out_of_range=getattr(args, "out_of_range", "auto"))


def height_from_file(args) -> None:
    """``--markers isb`` on a C3D with ``--model human`` and no ``--height``: the subject's height from
    the file (PROCESSING:Height) when it has one (printed)."""
    if getattr(args, "markers", None) is None or getattr(args, "height", None) is not None:
        return
    if getattr(args, "model", None) != "human" or Path(args.observations).suffix.lower() != ".c3d":
        return
    from camo_sbi.io.c3d import c3d_subject_height

    h = c3d_subject_height(args.observations)
    if h is not None:
        args.height = h
        print(f"subject height {h:.3f} m (the C3D file's PROCESSING:Height): the model is built for it")
