"""OpenSim motion and storage files (``.mot``, ``.sto``): joint angles a lab's own pipeline computed.

The format: a header of ``key=value`` lines (and a free first line, the name) ended by a line
``endheader``; then a line of tab- (or space-) separated column labels starting with ``time``;
then one row of numbers per frame::

    arm_session
    version=1
    nRows=3
    nColumns=10
    inDegrees=yes
    endheader
    time	torso_flexion	torso_rotation	...
    0.00	3.1	-0.4	...

Columns named as the model's joints are read (every joint must be there; other columns, an
OpenSim model's other coordinates, are skipped and listed in the loader's info); rotational
values are in degrees when ``inDegrees=yes`` (OpenSim's default for .mot), radians when ``no``.
To use another model's coordinates, rename the columns to the camo_sbi model's joints (`camo-sbi
describe` lists them with their signs) after converting the angles to its conventions.

Refused with one error naming the file and the line: no ``endheader`` within `MAX_HEADER_LINES`
lines, an ``inDegrees`` other than yes/no, a row with another number of fields than the labels,
a field that is not a number (NaN and inf included), ``nRows`` disagreeing with the rows, times
that do not increase.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from camo_sbi.io.text import read_text

__all__ = ["MAX_HEADER_LINES", "read_mot"]

MAX_HEADER_LINES = 200


def read_mot(path, joint_names) -> dict:
    """{"time" (F,), "frames" (F,) line numbers, "columns" {joint: (F,) radians}, "skipped": [labels],
    "in_degrees": bool} from the OpenSim file ``path``."""
    path = Path(path)
    lines = read_text(path, "an OpenSim .mot/.sto").splitlines()
    header: dict[str, str] = {}
    end = None
    for i, line in enumerate(lines[:MAX_HEADER_LINES]):
        t = line.strip()
        if t.lower() == "endheader":
            end = i
            break
        key, sep, value = t.partition("=")
        if sep:
            header[key.strip().lower()] = value.strip()
    if end is None:
        raise ValueError(f"{path}: no 'endheader' line within the first {MAX_HEADER_LINES} lines: not an OpenSim "
                         f".mot/.sto file")
    deg_text = header.get("indegrees", "yes").lower()
    if deg_text not in ("yes", "no"):
        raise ValueError(f"{path}: header inDegrees={header['indegrees']!r}; expected yes or no")
    in_degrees = deg_text == "yes"
    k = end + 1
    while k < len(lines) and not lines[k].strip():
        k += 1
    if k >= len(lines):
        raise ValueError(f"{path}: line {end + 2}: the column labels are missing after endheader")
    labels = lines[k].split("\t") if "\t" in lines[k] else lines[k].split()
    labels = [s.strip() for s in labels]
    if not labels or labels[0].lower() != "time":
        raise ValueError(f"{path}: line {k + 1}: the first column must be 'time', got {labels[0] if labels else ''!r}")
    dup = [c for c in labels if labels.count(c) > 1]
    if dup:
        raise ValueError(f"{path}: line {k + 1}: column {dup[0]!r} appears twice")
    missing = [j for j in joint_names if j not in labels]
    if missing:
        raise ValueError(f"{path}: column {missing[0]!r} is missing (every model joint needs a column; the model's "
                         f"joints, in order: {', '.join(joint_names)}; missing: {', '.join(missing)})")
    rows, where = [], []
    for n, line in enumerate(lines[k + 1:], start=k + 2):
        if not line.strip():
            continue
        fields = line.split("\t") if "\t" in line else line.split()
        if len(fields) != len(labels):
            raise ValueError(f"{path}: line {n}: has {len(fields)} fields, the labels have {len(labels)}")
        try:
            vals = [float(f) for f in fields]
        except ValueError:
            bad = next(f for f in fields if not _is_number(f))
            raise ValueError(f"{path}: line {n}: not a number: {bad.strip()[:40]!r}") from None
        if not all(np.isfinite(vals)):
            col = labels[int(np.flatnonzero(~np.isfinite(vals))[0])]
            raise ValueError(f"{path}: column {col!r}, line {n}: NaN or inf")
        rows.append(vals)
        where.append(n)
    if len(rows) < 2:
        raise ValueError(f"{path}: has {len(rows)} rows; a reach needs two or more")
    if "nrows" in header:
        try:
            n_rows = int(header["nrows"])
        except ValueError:
            raise ValueError(f"{path}: header nRows={header['nrows']!r} is not an integer") from None
        if n_rows != len(rows):
            raise ValueError(f"{path}: header nRows={n_rows} but the file has {len(rows)} rows (truncated?)")
    data = np.asarray(rows)
    time = data[:, 0]
    bad = np.flatnonzero(np.diff(time) <= 0)
    if bad.size:
        raise ValueError(f"{path}: column 'time', line {where[bad[0] + 1]}: time {time[bad[0] + 1]:g} does not "
                         f"increase (previous {time[bad[0]]:g})")
    cols = {j: data[:, labels.index(j)] for j in joint_names}
    if in_degrees:
        cols = {j: np.radians(v) for j, v in cols.items()}
    skipped = [c for c in labels[1:] if c not in joint_names]
    return {"time": time, "frames": np.asarray(where), "columns": cols, "skipped": skipped, "in_degrees": in_degrees}


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
