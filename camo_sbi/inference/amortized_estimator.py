"""The amortized estimator's settings, object and file: `TrainConfig`, `AmortizedEstimator`, `load_estimator`.

An estimator holds one trained flow per observation space and the metadata needed to check
a task against it and to rebuild the flows (`amortized` trains and runs it). Files: one
``torch.save`` dict {"format", "metadata" (JSON text), "state_dict"} read with
``torch.load(weights_only=True)``; the metadata (format, model fingerprint, prior box,
settings, feature masks, training cost, the payload's sha256, `payload_sha256`, verified
before anything is built) is checked against every task before use. Loading rebuilds each
NSF as `sbi_adapter.NsfReader` from the metadata and loads only its weights: no sbi import,
the same draws (MAF flows, sbi embedding nets and one-input flows are rebuilt through sbi).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch

from camo_sbi._io import atomic_write_bytes
from camo_sbi._validation import (
    InputError,
    check_bool,
    check_choice,
    check_positive_float,
    check_positive_int,
    renamed_fields,
)
from camo_sbi.inference import sbi_adapter
from camo_sbi.inference.amortized_data import (
    conditions,
    fingerprint_differences,
    model_fingerprint,
    seed_int,
)
from camo_sbi.inference.amortized_flows import SET_EMBEDDING, Flow, SetFlow, new_flow, uses_reader
from camo_sbi.inference.flow_space import from_unconstrained, torch_threads
from camo_sbi.inference.npe import check_training_settings
from camo_sbi.inference.npe_posterior import NpePosterior
from camo_sbi.task import SPACES, NoiseModel

__all__ = ["FAST_SET_TRAINING", "FORMAT", "FORMS", "AmortizedEstimator", "TrainConfig", "check_metadata", "from_bytes",
           "load_estimator", "payload_sha256"]

FORMAT = "camo_sbi.amortized/2"  # /2: the metadata carries the payload's sha256
_FORMAT_1 = "camo_sbi.amortized/1"
_DTYPES = {"float32": torch.float32, "float64": torch.float64}
FORMS = ("set", "per-reach")
_START_TOL = 1e-6  # radians: an observed start this close to the estimator's counts as the same
_BOX_TOL = 1e-9

# The optimiser settings a TrainConfig takes when they are left None, per form: for now the same
# for both. FAST_SET_TRAINING is the faster set-form alternative of
# benchmarks/bench_amortized_train.py (`camo-sbi amortize --fast`): it reaches the default's
# validation loss several times sooner but is more over-confident, so it is NOT the default
# (the numbers: docs/performance.md); on the per-reach MAF toy of
# tests/test_amortized.py it moved an upper limit 5.6 posterior sd off.
_OPTIMISER_DEFAULTS = {
    "set": {"training_batch_size": 512, "learning_rate": 1e-3, "lr_schedule": "constant", "max_epochs": 40},
    "per-reach": {"training_batch_size": 512, "learning_rate": 1e-3, "lr_schedule": "constant", "max_epochs": 40},
}
FAST_SET_TRAINING = {"training_batch_size": 2048, "learning_rate": 3e-3, "lr_schedule": "cosine", "max_epochs": 30}


@renamed_fields(simulation_batch_size="chunk_size")
@dataclass(frozen=True)
class TrainConfig:
    """How an amortized estimator is trained (all of it is stored in the file's metadata).

    Attributes:
        simulations: simulated reaches (one trajectory each).
        form: "set" (default: one flow q(theta | set of 1..max_set reaches) behind a
            permutation-invariant set embedding, `SetFlow`; the simulations are max_set
            reaches of each of simulations // max_set limit vectors; inference is one flow
            sample) or "per-reach" (one flow q(theta | one reach), combined over a person's
            reaches by the i.i.d. rule and sampled by `AmortizedConfig.combine`). The set form
            is the default because it calibrates and the per-reach product does not (docs/user-guide/amortized.md;
            docs/studies/amortized_measurements.md).
        max_set: the largest set of reaches the "set" form is trained on (and accepts).
        spaces: observation spaces to train a flow for ("joint", "cartesian" or both; the
            same simulations serve every space).
        noise: observation-noise model applied to the simulated trajectories (seeded).
        n_points, include_length: the trajectory summary (`trajectory_summary`).
        density_estimator: "nsf" (default; sbi's neural spline flow, coupling layers: one pass
            per transform to sample) or "maf" (sbi's masked autoregressive flow: sampling takes
            one pass per coordinate and transform, slower; and in nflows' MADE the
            first coordinate of each transform does not see the condition: on the 2-limit toy
            of the tests, with its seed and 3 transforms, one limit came out the same for every
            set of reaches, at its prior). The per-reach measurements were made with "maf".
        hidden_features, num_transforms: flow size.
        embedding_dim, embedding_hidden: None, or an MLP embedding of the condition (3 layers of
            ``embedding_hidden`` units, ``embedding_dim`` outputs) trained with the flow.
        training_batch_size, learning_rate, lr_schedule, validation_fraction, stop_after_epochs,
        max_epochs: maximum-likelihood training with early stopping (a batch holds
            ``training_batch_size`` reaches: for the set form that many // max_set sets;
            ``lr_schedule`` "cosine" lowers the rate along a half cosine over ``max_epochs``,
            "constant" keeps it). Left None, training_batch_size, learning_rate, lr_schedule
            and max_epochs take the form's defaults (`_OPTIMISER_DEFAULTS`: 512 reaches, 1e-3,
            constant, 40 epochs for both forms; training times: docs/user-guide/amortized.md).
            ``FAST_SET_TRAINING`` (2048, 3e-3, cosine, 30 epochs)
            reaches the same validation loss sooner but calibrates worse
            (`benchmarks/bench_amortized_train.py`, docs/performance.md), so it is
            an option (`amortize --fast`), not the default.
            `dataclasses.replace` keeps resolved values: replace ``form`` on a config built
            with the other form's defaults and they stay.
        max_train_seconds: per space, stop after the epoch that crosses it (None: no limit).
        chunk_size: trajectories per ``simulate`` call (old name: ``simulation_batch_size``).
        sim_dtype: "float32" or "float64" for the simulations.
        n_threads: torch intra-op threads while training (None: unchanged).
        balance: > 0 adds balanced NPE's penalty (Delaunoy et al. 2023) with this weight to
            the training loss (`sbi_adapter.fit_density_estimator`); 0 (default): plain
            maximum likelihood.
    """

    simulations: int = 200_000
    form: str = "set"
    max_set: int = 10
    spaces: tuple[str, ...] = ("joint",)
    noise: NoiseModel = field(default_factory=NoiseModel)
    n_points: int = 20
    include_length: bool = True
    density_estimator: str = "nsf"
    hidden_features: int = 64
    num_transforms: int = 5
    embedding_dim: int | None = None
    embedding_hidden: int = 128
    training_batch_size: int | None = None
    learning_rate: float | None = None
    validation_fraction: float = 0.05
    stop_after_epochs: int = 8
    max_epochs: int | None = None
    max_train_seconds: float | None = None
    chunk_size: int = 10_000
    sim_dtype: str = "float32"
    n_threads: int | None = 1
    balance: float = 0.0
    lr_schedule: str | None = None

    def __post_init__(self):
        check_positive_int(self.simulations, "simulations", minimum=10)
        check_positive_float(self.balance, "balance", allow_zero=True)
        check_choice(self.form, FORMS, "form")
        for name, value in _OPTIMISER_DEFAULTS[self.form].items():  # None: the form's measured default
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)
        check_choice(self.lr_schedule, sbi_adapter.LR_SCHEDULES, "lr_schedule")
        check_positive_int(self.max_set, "max_set", minimum=2)
        if self.form == "set" and self.simulations < 10 * self.max_set:
            raise ValueError(f"simulations: the set form needs at least {10 * self.max_set} (10 sets of "
                             f"max_set={self.max_set} reaches), got {self.simulations}")
        spaces = (self.spaces,) if isinstance(self.spaces, str) else tuple(self.spaces)
        if not spaces or len(set(spaces)) != len(spaces):
            raise ValueError(f"spaces: expected one or more distinct spaces of {SPACES}, got {self.spaces!r}")
        for s in spaces:
            check_choice(s, SPACES, "spaces")
        object.__setattr__(self, "spaces", spaces)
        if not isinstance(self.noise, NoiseModel):
            raise TypeError(f"noise: expected a NoiseModel, got {type(self.noise).__name__}")
        check_positive_int(self.n_points, "n_points")
        check_bool(self.include_length, "include_length")
        check_choice(self.density_estimator, sbi_adapter.FLOW_KINDS, "density_estimator")
        check_positive_int(self.hidden_features, "hidden_features")
        check_positive_int(self.num_transforms, "num_transforms")
        if self.embedding_dim is not None:
            check_positive_int(self.embedding_dim, "embedding_dim")
        check_positive_int(self.embedding_hidden, "embedding_hidden")
        check_training_settings(self)
        if self.max_train_seconds is not None:
            check_positive_float(self.max_train_seconds, "max_train_seconds")
        check_positive_int(self.chunk_size, "chunk_size")
        check_choice(self.sim_dtype, _DTYPES, "sim_dtype")
        if self.n_threads is not None:
            check_positive_int(self.n_threads, "n_threads")

    @property
    def reaches_per_theta(self) -> int:
        """Simulated reaches per training limit vector: max_set for the set form, 1 per reach."""
        return self.max_set if self.form == "set" else 1

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["spaces"] = list(self.spaces)
        return d

    @classmethod
    def from_json(cls, d: dict) -> TrainConfig:
        d = dict(d)
        d["noise"] = NoiseModel(**d["noise"])
        d["spaces"] = tuple(d["spaces"])
        d.setdefault("balance", 0.0)  # files written before the setting existed
        d.setdefault("lr_schedule", "constant")
        if "simulation_batch_size" in d:  # files written before the vocabulary was unified
            d["chunk_size"] = d.pop("simulation_batch_size")
        return cls(**d)


class AmortizedEstimator:
    """Per-reach flows q(theta | goal, trajectory) for one body model, one per space.

    Build with `train`, reload with `load_estimator`. ``metadata`` holds everything needed
    to check a task against it and to rebuild the flows; ``flows`` maps a space to its flow.
    """

    def __init__(self, metadata: dict, flows: dict[str, Flow]):
        self.metadata = metadata
        self.flows = {k: f.eval() for k, f in flows.items()}
        self.settings = TrainConfig.from_json(metadata["settings"])
        self.low = torch.tensor(metadata["prior"]["low"], dtype=torch.float64)
        self.high = torch.tensor(metadata["prior"]["high"], dtype=torch.float64)
        self.free_mask = self.high > self.low
        self.start = torch.tensor(metadata["fingerprint"]["start"], dtype=torch.float64)
        self.noise = NoiseModel(**metadata["settings"]["noise"])
        self.path: str | None = None

    @property
    def model(self) -> str:
        return self.metadata["model"]

    @property
    def spaces(self) -> tuple[str, ...]:
        return tuple(self.flows)

    @property
    def training_simulations(self) -> int:
        return int(self.metadata["training_simulations"])

    @property
    def training_time(self) -> float:
        return float(self.metadata["training_time"])

    # -- use

    def check_task(self, task, observations, space: str) -> None:
        """`InputError` (a ValueError naming what differs) unless ``task`` is one this estimator was trained for."""
        name = self.path or "the estimator"
        if space not in self.flows:
            raise InputError(f"space: {name} has flows for {list(self.flows)} only, not {space!r}; "
                             f"train one with --space {space}")
        diff = fingerprint_differences(self.metadata["fingerprint"], model_fingerprint(task.simulator))
        if diff:
            raise InputError(f"estimator: {name} was trained for model {self.model!r}; the task's simulator "
                             f"differs in {', '.join(diff)}")
        prior = task.prior
        if (prior.low.shape != self.low.shape or not torch.allclose(prior.low, self.low, atol=_BOX_TOL, rtol=0)
                or not torch.allclose(prior.high, self.high, atol=_BOX_TOL, rtol=0)):
            raise InputError(f"task.prior: differs from the prior {name} was trained under (the model's full "
                             f"range split at its default start, no fixed joints); retrain for this prior")
        for i, o in enumerate(observations):
            if not torch.allclose(o.start, self.start, atol=_START_TOL, rtol=0):
                raise InputError(f"observations: reach {i} starts at {o.start.tolist()}, but {name} was trained "
                                 f"for reaches from the model's default start {self.start.tolist()}")
        if task.noise != self.noise:
            raise InputError(f"task.noise: the task's observation noise {task.noise} differs from the noise "
                             f"{name} was trained with ({self.noise}); retrain with --noise-joint-deg / "
                             f"--noise-ee-mm matching the recordings")
        if self.form == "set":
            self._check_set_size(len(observations))

    def _check_set_size(self, n: int) -> None:
        k = self.settings.max_set
        if n > k:
            raise InputError(f"observations: {n} reaches, but the set estimator {self.path or ''} was "
                             f"trained on sets of at most max_set={k}; pass at most {k} or retrain")

    def conditions(self, observations, space: str) -> torch.Tensor:
        """(N, D) float32 network conditions of observed reaches (kept features only)."""
        keep = torch.tensor(self.metadata["features"][space]["keep"], dtype=torch.bool)
        rows = []
        for o in observations:
            traj = o.trajectory(space).to(torch.float64)
            rows.append(conditions(traj, torch.tensor([traj.shape[0]]), o.goal, self.settings)[0, keep])
        return torch.stack(rows).float()

    @property
    def form(self) -> str:
        return self.settings.form

    def set_condition(self, observations, space: str) -> torch.Tensor:
        """(1, K * (F + 1)) the packed set condition of 1..max_set observed reaches (set form)."""
        x = self.conditions(observations, space)
        k = self.settings.max_set
        self._check_set_size(x.shape[0])
        sets = torch.zeros(1, k, x.shape[1])
        sets[0, : x.shape[0]] = x
        valid = torch.arange(k)[None] < x.shape[0]
        return SetFlow.pack(sets, valid)

    @torch.no_grad()
    def sample_set(self, observations, space: str, n: int, seed: int, *, n_threads: int | None = 1):
        """(n, 2n) float64 draws of q(theta | the set of reaches) and their log densities (theta coordinates)."""
        flow = self.flows[space]
        lo, w = self.low[self.free_mask], (self.high - self.low)[self.free_mask]
        # everything under n_threads: small element-wise ops on the default threads cost up to
        # 100x more on a busy machine (measured: logsigmoid of (1000, 14) 49 ms vs 0.07 ms)
        with torch.random.fork_rng(devices=[]), torch_threads(n_threads):
            cond = self.set_condition(observations, space)
            torch.manual_seed(seed)
            z, lp = flow.sample_and_log_prob((n,), cond)
            z, lp = z.reshape(n, -1), lp.reshape(-1).double()
            free, logdet = from_unconstrained(z, lo, w, "logit")
            theta = self.low.repeat(n, 1)
            theta[:, self.free_mask] = free
            return theta, lp - logdet

    def posterior(self, observations, space: str, *, n_threads: int | None = 1) -> NpePosterior:
        """The combined posterior of the reaches (`NpePosterior`, the same flow N times)."""
        x = self.conditions(observations, space)
        flow = self.flows[space]
        return NpePosterior([flow] * x.shape[0], list(x), self.low, self.high,
                                theta_transform="logit",
                                n_threads=n_threads, info={"estimator": self.path, "space": space})

    def single_reach_posterior(self, space: str, *, chunk: int = 256) -> _SingleReach:
        """q(theta_free | x) for batches of raw conditions: sbi's ``sample_batched`` interface."""
        return _SingleReach(self, space, chunk)

    # -- persistence

    def to_bytes(self) -> bytes:
        state = {f"{space}.{k}": v.detach().cpu().clone() for space, f in self.flows.items()
                 for k, v in f.state_dict().items()}
        metadata = {**self.metadata, "sha256": payload_sha256(self.metadata, state)}
        buf = io.BytesIO()
        torch.save({"format": FORMAT, "metadata": json.dumps(metadata, sort_keys=True),
                    "state_dict": state}, buf)
        return buf.getvalue()

    def save(self, path) -> Path:
        """Write the estimator atomically to ``path`` (state dict + JSON metadata in one file)."""
        path = Path(path)
        atomic_write_bytes(path, self.to_bytes())
        return path

    def describe(self) -> str:
        m = self.metadata
        form = (f"set form (sets of 1..{self.settings.max_set} reaches)" if self.form == "set"
                else "per-reach form (combined by the i.i.d. rule)")
        lines = [f"amortized estimator for model {m['model']!r}: {form}, {self.settings.density_estimator} flow, "
                 f"spaces {', '.join(self.flows)}, {m['training_simulations']} training simulations, "
                 f"{m['training_time']:.1f} s to train",
                 f"  noise: {self.noise}; summary: {self.settings.n_points} points + length, goal prepended"]
        for space, info in m["training"].items():
            lines.append(f"  {space}: {m['features'][space]['n_kept']} features, {info['epochs']} epochs "
                         f"({info['stopped']}), best validation loss {info['best_validation_loss']:.3f}, "
                         f"{info['time_train']:.1f} s")
        return "\n".join(lines)


class _SingleReach:
    """sbi-style posterior of ONE condition row (one reach, or one packed set for the set form):
    ``sample_batched((n,), x)`` -> (n, B, n_free) theta draws."""

    def __init__(self, est: AmortizedEstimator, space: str, chunk: int):
        self._flow = est.flows[space]
        self._lo = est.low[est.free_mask]
        self._w = (est.high - est.low)[est.free_mask]
        self._chunk = chunk

    @torch.no_grad()
    def sample_batched(self, sample_shape, x, show_progress_bars: bool = False, **kwargs):
        n = int(torch.Size(sample_shape).numel())
        x = torch.as_tensor(x, dtype=torch.float32)
        out = []
        for s in range(0, x.shape[0], self._chunk):
            z = self._flow.sample((n,), x[s : s + self._chunk]).to(torch.float64)
            out.append(from_unconstrained(z.reshape(-1, z.shape[-1]), self._lo, self._w,
                                              "logit")[0].reshape(z.shape))
        return torch.cat(out, dim=1).float()


def payload_sha256(metadata: dict, state: dict) -> str:
    """sha256 of an estimator file's payload: its metadata (without the "sha256" entry, as sorted
    JSON) and every tensor of its state dict (key, dtype, shape and raw bytes, in key order)."""
    h = hashlib.sha256(json.dumps({k: v for k, v in metadata.items() if k != "sha256"}, sort_keys=True).encode())
    for key in sorted(state):
        t = state[key].detach().cpu().contiguous()
        h.update(f"\n{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


_MAX_SET = 10_000  # reaches in one set: far above any recording, small enough to allocate


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def check_metadata(meta: dict, state: dict, name: str = "estimator") -> TrainConfig:
    """The settings of an estimator file's metadata, after checking its schema, types and sizes
    against the weights it holds, before anything is built (a re-signed, edited file cannot make
    the loader allocate what its weights do not: a flow of ``hidden_features`` units has at least
    ``hidden_features**2`` weights, one of ``n_kept`` inputs at least ``n_kept``). ValueError naming
    the file and the metadata key otherwise."""

    def bad(key: str, what: str) -> ValueError:
        return ValueError(f"estimator: {name}'s metadata: {key}: {what} (the file was edited or is not "
                          f"camo_sbi's; retrain it with `camo-sbi amortize`)")

    types = {"model": (str, "a string"), "fingerprint": (dict, "a table"), "prior": (dict, "a table"),
             "settings": (dict, "a table"), "features": (dict, "a table"), "training": (dict, "a table")}
    for key, (kind, text) in types.items():
        if key not in meta:
            raise bad(key, "missing")
        if not isinstance(meta[key], kind):
            raise bad(key, f"expected {text}, got {type(meta[key]).__name__}")
    for key in ("seed", "training_simulations"):
        v = meta.get(key)
        if not _is_int(v) or not 0 <= v < 2**63:
            raise bad(key, f"expected an integer in [0, 2**63), got {v!r}")
    if not _is_number(meta.get("training_time")):
        raise bad("training_time", f"expected a number, got {meta.get('training_time')!r}")
    weights = sum(int(t.numel()) for t in state.values() if isinstance(t, torch.Tensor))
    prior = meta["prior"]
    for key in ("low", "high"):
        v = prior.get(key)
        if not isinstance(v, list) or not v or len(v) % 2 or not all(_is_number(x) for x in v):
            raise bad(f"prior.{key}", "expected a non-empty list of an even number of finite numbers")
    if len(prior["low"]) != len(prior["high"]) or any(lo > hi for lo, hi in zip(prior["low"], prior["high"],
                                                                                strict=True)):
        raise bad("prior", "low and high differ in length or low > high")
    n_free = sum(1 for lo, hi in zip(prior["low"], prior["high"], strict=True) if hi > lo)
    if not 1 <= n_free <= weights:
        raise bad("prior", f"{n_free} free parameters for {weights} weights")
    start = meta["fingerprint"].get("start")
    if not isinstance(start, list) or 2 * len(start) != len(prior["low"]) or not all(_is_number(x) for x in start):
        raise bad("fingerprint.start", f"expected {len(prior['low']) // 2} finite numbers")
    try:
        settings = TrainConfig.from_json(meta["settings"])
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        what = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
        raise bad("settings", what) from None
    sizes = {"num_transforms": settings.num_transforms, "embedding_hidden": settings.embedding_hidden,
             "embedding_dim": settings.embedding_dim or 1, "hidden_features": settings.hidden_features ** 2}
    for key, need in sizes.items():
        if need > weights:
            raise bad(f"settings.{key}", f"{getattr(settings, key)} is larger than the {weights} weights the file "
                                         f"holds allow")
    if settings.max_set > _MAX_SET:
        raise bad("settings.max_set", f"{settings.max_set} reaches in a set, at most {_MAX_SET}")
    extra = sorted(set(meta["training"]) - set(settings.spaces))
    if extra:
        raise bad("training", f"space {extra[0]!r} is not one of settings.spaces {list(settings.spaces)}")
    for space in settings.spaces:
        f = meta["features"].get(space)
        if not isinstance(f, dict):
            raise bad(f"features.{space}", "missing")
        keep, n_kept = f.get("keep"), f.get("n_kept")
        if not isinstance(keep, list) or not keep or not all(isinstance(k, bool) for k in keep):
            raise bad(f"features.{space}.keep", "expected a non-empty list of true/false")
        if not _is_int(n_kept) or n_kept != sum(keep) or not 1 <= n_kept <= weights:
            raise bad(f"features.{space}.n_kept", f"{n_kept!r} is not the {sum(keep)} features its keep list "
                                                  f"keeps (at most {weights}, the weights the file holds)")
        if settings.n_points > len(keep):
            raise bad("settings.n_points", f"{settings.n_points} points but {len(keep)} features")
        info = meta["training"].get(space)
        need = {"epochs": _is_int, "stopped": lambda v: isinstance(v, str), "time_train": _is_number,
                "best_validation_loss": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)}
        if not isinstance(info, dict) or any(k not in info or not ok(info[k]) for k, ok in need.items()):
            raise bad(f"training.{space}", f"expected a table of {', '.join(need)}")
    return settings


def from_bytes(data: bytes, name: str = "estimator") -> AmortizedEstimator:
    """Rebuild an estimator from `AmortizedEstimator.to_bytes` (``torch.load(weights_only=True)``).

    The payload's sha256 (`payload_sha256`, stored in the metadata) is verified before anything
    is built: a damaged or edited file is a ValueError naming it. NSF flows are rebuilt as
    `sbi_adapter.NsfReader` (same weights, same draws, no sbi import); others through sbi.
    """
    try:
        blob = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling error means "not our file"
        raise ValueError(f"estimator: {name} is not a camo_sbi amortized estimator or is damaged "
                         f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from exc
    if not isinstance(blob, dict) or blob.get("format") not in (FORMAT, _FORMAT_1):
        found = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise ValueError(f"estimator: {name} has format {found!r}, expected {FORMAT!r} (retrain it with this "
                         f"version of camo_sbi)")
    missing = [k for k in ("metadata", "state_dict") if k not in blob]
    if missing or not isinstance(blob["metadata"], str) or not isinstance(blob["state_dict"], dict):
        raise ValueError(f"estimator: {name} has no valid {' or '.join(missing) or 'metadata and state_dict'} "
                         f"entry (damaged, or not written by `camo-sbi amortize`)")
    if blob["format"] == _FORMAT_1:
        raise ValueError(f"estimator: {name} has format {_FORMAT_1!r}, written before estimator files carried a "
                         f"checksum; retrain it with `camo-sbi amortize` (format {FORMAT!r})")
    try:
        meta = json.loads(blob["metadata"])
    except (ValueError, RecursionError) as exc:  # RecursionError: nested thousands of levels deep
        raise ValueError(f"estimator: {name}'s metadata is not valid JSON (damaged file)") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise ValueError(f"estimator: {name}'s metadata has format {found!r}, expected {FORMAT!r}")
    stored = meta.get("sha256")
    if not isinstance(stored, str) or stored != payload_sha256(meta, blob["state_dict"]):
        raise ValueError(f"estimator: {name} fails its sha256 check (stored {str(stored)[:12]}..., the payload "
                         f"differs): the file is damaged or was edited; retrain it or restore a copy")
    settings = check_metadata(meta, blob["state_dict"], name)
    if settings.form == "set" and meta.get("set_embedding") != SET_EMBEDDING:
        raise ValueError(f"estimator: {name} is a set-form estimator with set embedding "
                         f"{meta.get('set_embedding', 'the first, experimental DeepSet')!r}, this version reads "
                         f"{SET_EMBEDDING!r} only; retrain it with `camo-sbi amortize`")
    n_in = int(sum(1 for lo, hi in zip(meta["prior"]["low"], meta["prior"]["high"], strict=True) if hi > lo))
    flows = {}
    for k, space in enumerate(settings.spaces):
        prefix = f"{space}."
        state = {key[len(prefix):]: v for key, v in blob["state_dict"].items() if key.startswith(prefix)}
        flow = new_flow(settings, n_in, meta["features"][space]["n_kept"], seed_int(meta["seed"], 3, k),
                         reader=uses_reader(settings, n_in))
        try:
            flow.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            raise ValueError(f"estimator: {name}'s {space} weights do not fit the flow its metadata describes: "
                             f"{_layout_versions(meta)}; retrain it with `camo-sbi amortize` under this version "
                             f"({str(exc).splitlines()[0]})") from exc
        flows[space] = flow
    return AmortizedEstimator(meta, flows)


def _layout_versions(meta: dict) -> str:
    """Which sbi wrote a file and which weight layouts this version reads (without importing sbi:
    `sbi_adapter.NsfReader` exists so that loading does not)."""
    from importlib import metadata as dist

    lo, hi = sbi_adapter.SBI_SUPPORTED
    written = (meta.get("versions") or {}).get("sbi", "an unrecorded version")
    try:
        installed = dist.version("sbi")
    except dist.PackageNotFoundError:
        installed = "not installed"
    return (f"the file was written with sbi {written}; this camo_sbi reads the flow layout of sbi "
            f">= {lo[0]}.{lo[1]}, < {hi[0]}.{hi[1]} (installed: sbi {installed})")


_CACHE: dict[tuple, AmortizedEstimator] = {}


def load_estimator(path) -> AmortizedEstimator:
    """Load an estimator file (cached per process by path, size and modification time)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"estimator: expected a path, got {type(path).__name__}")
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"estimator: no such file {str(p)!r} (train one with `camo-sbi amortize`)")
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _CACHE:
        est = from_bytes(p.read_bytes(), repr(str(p)))
        est.path = str(p)
        _CACHE.clear()  # one estimator at a time is what every caller needs
        _CACHE[key] = est
    return _CACHE[key]
