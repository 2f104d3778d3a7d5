"""Issue 36's hostile-input test: random and truncated bytes (hypothesis) fed to every reader of a
user's file: URDF, CSV, NPZ, C3D, BVH (and its map), JSON (frame, marker positions, limits),
TOML (study) and the amortized estimator file.

Each example must end within `EXAMPLE_SECONDS` either in a result or in a ValueError, TypeError
or OSError whose message names the file; any other exception type, or a hang (a SIGALRM raises
`Hang`, a BaseException the readers cannot swallow), fails the test. A crash in C code (ezc3d
segfaults on some damaged C3D files) would kill the test process: the C3D reader opens every
file in a child process first (`camo_sbi.io.c3d._probe`), so it cannot.

The default tier runs `FAST` examples per reader (derandomized: the same examples on every run);
``pytest -m slow`` runs `SLOW`.
"""

from __future__ import annotations

import contextlib
import json
import signal
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from tests import test_infer_cli  # noqa: E402
from tests.test_infer_cli import DATA  # noqa: E402

sim = test_infer_cli.sim  # the arm7 model fixture

EXAMPLE_SECONDS = 30  # issue 36: every case ends within 30 s
FAST, SLOW = 6, 150
ALLOWED = (ValueError, TypeError, OSError)


class Hang(BaseException):
    """An example ran longer than EXAMPLE_SECONDS."""


@contextlib.contextmanager
def _alarm(seconds: float):
    def handler(signum, frame):
        raise Hang(f"no result within {seconds} s")

    old = signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _mutations(good: bytes):
    """Random bytes, a truncation of ``good``, ``good`` with a few bytes overwritten, or a cut
    followed by random bytes."""
    n = len(good)
    flips = st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=12)

    def flip(pairs):
        b = bytearray(good)
        for i, v in pairs:
            b[i] = v
        return bytes(b)

    return st.one_of(
        st.binary(max_size=3000),
        st.integers(0, n).map(lambda k: good[:k]),
        flips.map(flip),
        st.tuples(st.integers(0, n), st.binary(max_size=200)).map(lambda t: good[:t[0]] + t[1]),
    )


def _check(read, path: Path, data: bytes, *, names_file: bool = True):
    """Write ``data`` to ``path``, call ``read(path)``: a result or an allowed error naming the file."""
    path.write_bytes(data)
    try:
        with _alarm(EXAMPLE_SECONDS):
            read(path)
    except ALLOWED as exc:
        msg = str(exc)
        assert "\n" not in msg.strip(), f"{type(exc).__name__} spans lines: {msg[:300]!r}"
        if names_file:
            assert path.name in msg, f"{type(exc).__name__} does not name {path.name}: {msg[:300]!r}"


def _fuzz(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def goods(sim, tmp_path_factory):
    """A valid file of every kind (bytes), and the BVH map that goes with the BVH."""
    from camo_sbi.experiments.models import load_limits
    from camo_sbi.experiments.simulate import simulate_recordings
    from camo_sbi.io.schema import save_recordings
    from camo_sbi.task import Observation
    from tests.test_mocap import write_bvh

    d = tmp_path_factory.mktemp("goods")
    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    obs = simulate_recordings(sim, theta, 2, seed=7)
    csv = save_recordings(d / "r.csv", obs, sim)
    npz = save_recordings(d / "r.npz", obs, sim)
    joint = tuple(Observation(o.start, sim.forward_kinematics(o.q[-1]).double(), o.q, None) for o in obs)
    bvh, _ = write_bvh(d / "r.bvh", joint, list(sim.joint_names), signs=[1] * 7, offsets=[0.0] * 7)
    from tests.test_cli_conventions import STUDY

    return {"csv": csv.read_bytes(), "npz": npz.read_bytes(), "bvh": bvh.read_bytes(),
            "bvh_map": bvh.with_suffix(".json").read_bytes(), "bvh_map_path": bvh.with_suffix(".json"),
            "c3d": (DATA / "session.c3d").read_bytes(), "urdf": (DATA / "arm7.urdf").read_bytes(),
            "frame": (DATA / "session_frame.json").read_bytes(),
            "markers": (DATA / "session_markers.json").read_bytes(),
            "limits": (DATA / "arm7_limits.json").read_bytes(), "study": STUDY.encode()}


def _readers(sim, goods):
    from camo_sbi.experiments.models import ModelSpec, load_limits
    from camo_sbi.experiments.run import load_study
    from camo_sbi.io.bvh import load_bvh_map
    from camo_sbi.io.frames import load_frame, load_marker_positions
    from camo_sbi.io.recordings import load_recording

    frame = load_frame(DATA / "session_frame.json")
    return {
        "csv": lambda p: load_recording(p, sim),
        "npz": lambda p: load_recording(p, sim),
        "bvh": lambda p: load_recording(p, sim, goal="final", bvh_map=goods["bvh_map_path"]),
        "bvh_map": lambda p: load_bvh_map(p, list(sim.joint_names)),
        "c3d": lambda p: load_recording(p, sim, goal="final", ee_markers=["TOOL"], frame=frame),
        "urdf": lambda p: ModelSpec(kind="urdf", urdf=str(p), ee="tool").build(),
        "frame": load_frame,
        "markers": lambda p: load_marker_positions(p, ["BASE_A", "BASE_B", "BASE_C"]),
        "limits": lambda p: load_limits(p, sim),
        "study": load_study,
    }


SUFFIX = {"csv": ".csv", "npz": ".npz", "bvh": ".bvh", "bvh_map": ".json", "c3d": ".c3d", "urdf": ".urdf",
          "frame": ".json", "markers": ".json", "limits": ".json", "study": ".toml"}


def _run_reader(kind: str, n: int, sim, goods, tmp_path):
    read = _readers(sim, goods)[kind]
    path = tmp_path / f"fuzzed{SUFFIX[kind]}"
    good = tmp_path / f"good{SUFFIX[kind]}"
    good.write_bytes(goods[kind])
    read(good)  # the unmutated file reads

    @_fuzz(n)
    @given(_mutations(goods[kind]))
    def body(data):
        _check(read, path, data)

    body()


@pytest.mark.timeout(600)
@pytest.mark.parametrize("kind", list(SUFFIX))
def test_every_reader_ends_in_a_result_or_a_named_error(kind, sim, goods, tmp_path):
    _run_reader(kind, FAST, sim, goods, tmp_path)


@pytest.mark.slow
@pytest.mark.timeout(3600)
@pytest.mark.parametrize("kind", list(SUFFIX))
def test_every_reader_survives_many_hostile_files(kind, sim, goods, tmp_path):
    _run_reader(kind, SLOW, sim, goods, tmp_path)


def _estimator_bytes() -> bytes:
    """A file shaped like an amortized estimator (format, metadata, state_dict) with a wrong
    checksum: every mutation of it must be refused by name, never built."""
    import io

    import torch

    from camo_sbi.inference.amortized_estimator import FORMAT

    buf = io.BytesIO()
    torch.save({"format": FORMAT, "metadata": json.dumps({"format": FORMAT, "sha256": "0" * 64}),
                "state_dict": {"joint.w": torch.zeros(4, 3)}}, buf)
    return buf.getvalue()


@pytest.mark.timeout(600)
def test_estimator_reader_ends_in_a_named_error(tmp_path):
    from camo_sbi.inference.amortized_estimator import load_estimator

    good = _estimator_bytes()
    path = tmp_path / "fuzzed.pt"

    @_fuzz(3 * FAST)
    @given(_mutations(good))
    def body(data):
        _check(load_estimator, path, data)

    body()
    path.write_bytes(good)
    with pytest.raises(ValueError, match="fuzzed.pt' fails its sha256 check"):
        load_estimator(path)


def test_the_alarm_fails_a_hang_rather_than_waiting(tmp_path):
    """The harness itself: a reader that loops forever is stopped and reported as `Hang`."""
    def forever(path):
        while True:
            np.zeros(1)

    with pytest.raises(Hang):
        with _alarm(0.2):
            forever(tmp_path)


def test_estimator_with_deeply_nested_metadata_is_refused_by_name(tmp_path):
    import io

    import torch

    from camo_sbi.inference.amortized_estimator import FORMAT, load_estimator

    buf = io.BytesIO()
    torch.save({"format": FORMAT, "metadata": "[" * 100_000, "state_dict": {}}, buf)
    (tmp_path / "deep.pt").write_bytes(buf.getvalue())
    with pytest.raises(ValueError, match=r"^estimator: '.*deep\.pt''s metadata is not valid JSON"):
        load_estimator(tmp_path / "deep.pt")
