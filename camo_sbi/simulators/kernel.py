"""The fused hot loop: a numba kernel generated from a `ChainSpec`.

For each (chain, dtype) `generate_source` writes straight-line Python: the forward
kinematics and position Jacobian of that very chain with its constant transforms baked
in (terms whose constant is exactly 0 are dropped, +-1 factors become signs, so a
quarter-turn URDF origin costs no arithmetic), followed by the controller step of
`controller.py` (closed-form 3x3 solve, no linalg call; in a float32 kernel the solve runs in
float64 when the damping is below float32 resolution, as `controller.py` says). Every float literal is wrapped
in the kernel's dtype ``F(...)`` so float32 maths never promotes to float64.

The source is written once to a cache directory (``$CAMO_SBI_KERNEL_CACHE``, else
``$XDG_CACHE_HOME/camo_sbi/kernels``, else ``~/.cache/camo_sbi/kernels``) under a name
keyed by the sha256 of that source (which holds only numbers and fixed text: no joint,
link or file name ever enters it), checked against that digest, then imported, so ``@njit(cache=True)`` reuses the compiled machine code across processes.
numba unpickles what it finds there, so the directory must be private: created with mode
0700, a real directory owned by this user that no one else can write (`check_cache_dir`).
If it is not, or a cache file stays unloadable after being deleted and rebuilt once, the
kernel is compiled in memory without caching (`KernelCacheWarning`); never from a shared
temporary directory.
The kernels are serial ``nogil`` functions of a row chunk ``(c, n_chunks)``; `kernel_simulate`
runs the chunks on the process's shared thread runner (`camo_sbi._threads`), one per CPU or
``NUMBA_NUM_THREADS``. Each sample is computed independently and sequentially, so results do
not depend on the number of threads. (Serial kernels compile faster than numba's
``parallel=True``/``prange``, and compilation is most of a new chain's cold start:
docs/studies/design_measurements.md.) Only ``simulate`` is
compiled when a kernel is loaded; ``fk`` (used by `kernel_fk`, the tests' check) compiles on its
first call.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import linecache
import os
import pickle
import sys
import threading
import types
import warnings
from pathlib import Path

import numpy as np

from camo_sbi._compiling import announce_compiling
from camo_sbi._io import atomic_write_bytes, check_private_dir, make_private_dir
from camo_sbi._threads import default_workers, run_chunks
from camo_sbi.simulators.chain import ChainSpec
from camo_sbi.simulators.controller import SOLVE64_BELOW_LAMBDA2

__all__ = ["KernelCacheWarning", "cache_dir", "check_cache_dir", "generate_source", "kernel_fk",
           "kernel_simulate", "load_kernel", "source_digest"]

GENERATOR_VERSION = "7"
_DTYPES = {np.dtype(np.float32): "float32", np.dtype(np.float64): "float64"}

# --------------------------------------------------------------------------- symbolic code
# An "entry" is a polynomial {factors (sorted tuple of variable names): coefficient}.
# Constants are the empty tuple. Entries are materialised into temporaries as soon as they
# hold more than one term, so expressions stay short.


def _const(c: float) -> dict:
    return {} if c == 0.0 else {(): float(c)}


def _var(name: str) -> dict:
    return {(name,): 1.0}


def _lin(pairs) -> dict:
    """sum_i c_i * entry_i for constant c_i."""
    out: dict = {}
    for c, e in pairs:
        if c == 0.0:
            continue
        for f, v in e.items():
            out[f] = out.get(f, 0.0) + c * v
    return {f: v for f, v in out.items() if v != 0.0}


def _mul(a: dict, b: dict) -> dict:
    out: dict = {}
    for fa, va in a.items():
        for fb, vb in b.items():
            f = tuple(sorted(fa + fb))
            out[f] = out.get(f, 0.0) + va * vb
    return {f: v for f, v in out.items() if v != 0.0}


def _add(*es) -> dict:
    return _lin([(1.0, e) for e in es])


class _Writer:
    def __init__(self, indent: str):
        self.indent = indent
        self.lines: list[str] = []
        self._n = 0

    def line(self, s: str) -> None:
        self.lines.append(self.indent + s)

    @staticmethod
    def expr(e: dict) -> str:
        if not e:
            return "F(0.0)"
        parts = []
        for f in sorted(e, key=lambda f: (len(f), f)):
            c = e[f]
            body = "*".join(f)
            if not f:
                parts.append(("+" if c > 0 else "-", f"F({float(abs(c))!r})"))
            elif abs(c) == 1.0:
                parts.append(("+" if c > 0 else "-", body))
            else:
                parts.append(("+" if c > 0 else "-", f"F({float(abs(c))!r})*{body}"))
        s = ("-" if parts[0][0] == "-" else "") + parts[0][1]
        for sign, p in parts[1:]:
            s += f" {sign} {p}"
        return s

    def mat(self, e: dict, name: str | None = None) -> dict:
        """Materialise ``e`` into a temporary (or ``name``) unless it is a signed single factor."""
        if name is None:
            if not e or (len(e) == 1 and len(next(iter(e))) <= 1):
                return e
            self._n += 1
            name = f"_t{self._n}"
        self.line(f"{name} = {self.expr(e)}")
        return _var(name)


def _fk(w: _Writer, spec: ChainSpec, name_x=("x0", "x1", "x2")):
    """Emit FK (and per-joint world axis/origin) for the chain; returns (p_ee, joints)."""
    R = [[_const(1.0 if r == c else 0.0) for c in range(3)] for r in range(3)]
    p = [_const(0.0)] * 3
    joints = []
    for k in range(spec.n_joints):
        org = spec.origins[k]
        M = [[w.mat(_lin([(org[j, c], R[r][j]) for j in range(3)])) for c in range(3)] for r in range(3)]
        po = [w.mat(_add(p[r], _lin([(org[j, 3], R[r][j]) for j in range(3)]))) for r in range(3)]
        a = spec.axes[k]
        z = [w.mat(_lin([(a[j], M[r][j]) for j in range(3)])) for r in range(3)]
        q = _var(f"q{k}")
        if spec.joint_types[k] == "revolute":
            w.line(f"cq{k} = math.cos(q{k})")
            w.line(f"sq{k} = math.sin(q{k})")
            C, S, ONE = _var(f"cq{k}"), _var(f"sq{k}"), _const(1.0)
            K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
            rot = [[_lin([(a[r] * a[c], ONE), ((1.0 if r == c else 0.0) - a[r] * a[c], C), (K[r, c], S)])
                    for c in range(3)] for r in range(3)]
            R = [[w.mat(_add(*[_mul(M[r][j], rot[j][c]) for j in range(3)])) for c in range(3)]
                 for r in range(3)]
            p = po
        else:
            R = M
            p = [w.mat(_add(po[r], _mul(q, z[r]))) for r in range(3)]
        joints.append((spec.joint_types[k], po, z))
    tip = spec.tip
    pe = [w.mat(_add(p[r], _lin([(tip[j, 3], R[r][j]) for j in range(3)])), name=name_x[r]) for r in range(3)]
    return pe, joints


def _solve(w: _Writer, out: _Writer, cols, n: int, cast: str, sfx: str) -> None:
    """Emit the damped step into ``out`` (at ``w``'s indent): r = v - J dq0 ; A = J J^T + lam2 I ;
    w = A^-1 r ; d = J^T w + dq0, in the kernel's dtype (``cast="F"``) or in float64 (``"D"``:
    the Jacobian, dq0, v and lambda^2 cast in, d cast back to F), temporaries suffixed ``sfx``."""
    J = range(n)
    if cast == "D":
        for k in J:
            for r in range(3):
                w.line(f"j{k}_{r}{sfx} = D({w.expr(cols[k][r])})")
        jc = [[_var(f"j{k}_{r}{sfx}") for r in range(3)] for k in J]
        for k in J:
            w.line(f"n{k}{sfx} = D(n{k})")
        for r in range(3):
            w.line(f"v{r}{sfx} = D(v{r})")
        w.line(f"lam2{sfx} = D(lam2)")
    else:
        jc = cols
    nv = [_var(f"n{k}{sfx}") for k in J]
    for r in range(3):
        w.mat(_lin([(1.0, _var(f"v{r}{sfx}"))] + [(-1.0, _mul(jc[k][r], nv[k])) for k in J]), name=f"r{r}{sfx}")
    for r, c in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        e = _add(*[_mul(jc[k][r], jc[k][c]) for k in J])
        if r == c:
            e = _add(e, _var(f"lam2{sfx}"))
        w.mat(e, name=f"a{r}{c}{sfx}")
    x = sfx
    for line in (
        f"i00{x} = a11{x} * a22{x} - a12{x} * a12{x}",
        f"i01{x} = a02{x} * a12{x} - a01{x} * a22{x}",
        f"i02{x} = a01{x} * a12{x} - a02{x} * a11{x}",
        f"i11{x} = a00{x} * a22{x} - a02{x} * a02{x}",
        f"i12{x} = a01{x} * a02{x} - a00{x} * a12{x}",
        f"i22{x} = a00{x} * a11{x} - a01{x} * a01{x}",
        f"idet{x} = {cast}(1.0) / (a00{x} * i00{x} + a01{x} * i01{x} + a02{x} * i02{x})",
        f"w0{x} = (i00{x} * r0{x} + i01{x} * r1{x} + i02{x} * r2{x}) * idet{x}",
        f"w1{x} = (i01{x} * r0{x} + i11{x} * r1{x} + i12{x} * r2{x}) * idet{x}",
        f"w2{x} = (i02{x} * r0{x} + i12{x} * r1{x} + i22{x} * r2{x}) * idet{x}",
    ):
        w.line(line)
    for k in J:
        e = _add(*[_mul(jc[k][r], _var(f"w{r}{sfx}")) for r in range(3)], nv[k])
        if cast == "D":
            w.mat(e, name=f"dd{k}{sfx}")
            w.line(f"d{k} = F(dd{k}{sfx})")
        else:
            w.mat(e, name=f"d{k}")
    out.lines.extend(w.lines)


def generate_source(spec: ChainSpec, dtype, *, cache: bool = True) -> str:
    """Python source of the numba module for ``spec`` in ``dtype`` (np.float32 / np.float64).

    ``cache``: the value of ``@njit(cache=...)`` (False for modules compiled in memory).
    """
    dt = _DTYPES[np.dtype(dtype)]
    jit = f"@njit(cache={bool(cache)}, nogil=True, error_model=\"numpy\")"
    n = spec.n_joints
    J = range(n)
    # No user string (URDF path, joint/link names, even the chain digest) ever enters the
    # source: only numbers computed here and fixed text. The module is named by its own
    # sha256 (`source_digest`), so the source identifies itself.
    head = [
        f'"""Generated by camo_sbi.simulators.kernel (v{GENERATOR_VERSION}): a serial chain of',
        f'{int(n)} joints in {dt}. Do not edit."""',
        "",
        "import math",
        "",
        "import numpy as np",
        "from numba import njit",
        "",
        f"F = np.{dt}",
        "D = np.float64",
        "",
    ]

    # ---- fk(q (B, n), out (B, 3))
    fkw = _Writer(" " * 8)
    _fk(fkw, spec)
    fk_src = [
        jit,
        "def fk(c, n_chunks, q, out):",
        "    B = q.shape[0]",
        "    for b in range(c * B // n_chunks, (c + 1) * B // n_chunks):",
        *[f"        q{k} = q[b, {k}]" for k in J],
        *fkw.lines,
        *[f"        out[b, {r}] = x{r}" for r in range(3)],
        "",
        "",
    ]

    # ---- simulate
    w = _Writer(" " * 12)
    pe, joints = _fk(w, spec)
    cols = []
    for typ, po, z in joints:
        if typ == "revolute":
            d = [w.mat(_lin([(1.0, pe[r]), (-1.0, po[r])])) for r in range(3)]
            col = [w.mat(_lin([(1.0, _mul(z[(r + 1) % 3], d[(r + 2) % 3])),
                               (-1.0, _mul(z[(r + 2) % 3], d[(r + 1) % 3]))])) for r in range(3)]
        else:
            col = z
        cols.append(col)
    step = _Writer(" " * 12)
    if dt == "float64":
        _solve(_Writer(" " * 12), step, cols, n, "F", "")
    else:  # float32: the solve in float64 when lambda^2 lies below float32 resolution (controller.py)
        step.line(f"if lam2 < F({SOLVE64_BELOW_LAMBDA2!r}):")
        _solve(_Writer(" " * 16), step, cols, n, "D", "_d")
        step.line("else:")
        _solve(_Writer(" " * 16), step, cols, n, "F", "")
    for k in J:  # the authors' hard-limit penalty (0 unless lg > 0 and q outside its limits)
        step.line(f"d{k} = d{k} + lg * (max(lo{k} - q{k}, F(0.0)) + max(q{k} - hi{k}, F(0.0)))")

    i3 = " " * 12
    i4 = " " * 16
    i5 = " " * 20
    sim_src = [
        jit,
        "def simulate(c, n_chunks, theta, goal, start, n_steps, tol, gain, lam2, max_cart, max_joint, null_gain,",
        "             kd, early_stop, lg, lbuf, lcap, q_out, x_out, length, reached):",
        "    B = theta.shape[0]",
        "    for b in range(c * B // n_chunks, (c + 1) * B // n_chunks):",
        *[f"        lo{k} = theta[b, {2 * k}]\n        hi{k} = theta[b, {2 * k + 1}]" for k in J],
        *[f"        md{k} = F(0.5) * (lo{k} + hi{k})" for k in J],
        *[f"        q{k} = start[b, {k}]" for k in J],
        *[f"        g{r} = goal[b, {r}]" for r in range(3)],
        "        length[b] = n_steps",
        "        reached[b] = False",
        *[f"        p{r} = F(0.0)" for r in range(3)],
        "        for t in range(n_steps):",
        *w.lines,
        *[f"{i3}q_out[b, t, {k}] = q{k}" for k in J],
        *[f"{i3}x_out[b, t, {r}] = x{r}" for r in range(3)],
        *[f"{i3}e{r} = g{r} - x{r}" for r in range(3)],
        # derivative term: the previous step's end-effector displacement (0 at the start)
        f"{i3}if t == 0:",
        *[f"{i4}p{r} = x{r}" for r in range(3)],
        *[f"{i3}dx{r} = x{r} - p{r}" for r in range(3)],
        *[f"{i3}p{r} = x{r}" for r in range(3)],
        f"{i3}if not early_stop:",
        f"{i4}if t == n_steps - 1:",
        f"{i5}reached[b] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) < tol",
        f"{i5}break",
        f"{i3}elif math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) < tol:",
        f"{i4}length[b] = t + 1",
        f"{i4}reached[b] = True",
        f"{i4}for u in range(t + 1, n_steps):",
        *[f"{i5}q_out[b, u, {k}] = q{k}" for k in J],
        *[f"{i5}x_out[b, u, {r}] = x{r}" for r in range(3)],
        f"{i4}break",
        f"{i3}if t == n_steps - 1:",
        f"{i4}break",
        *[f"{i3}v{r} = gain * e{r} - kd * dx{r}" for r in range(3)],
        f"{i3}vn = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)",
        f"{i3}if vn > max_cart:",
        f"{i4}sc = max_cart / vn",
        *[f"{i4}v{r} = v{r} * sc" for r in range(3)],
        *[f"{i3}n{k} = null_gain * (md{k} - q{k})" for k in J],
        # the authors' null-space push within lbuf of a limit (their upper term as written)
        f"{i3}if lg > F(0.0):",
        *[f"{i4}n{k} = n{k} + F(2.0) * lg * min(max(lo{k} + lbuf - q{k}, F(0.0)), lcap)"
          f" + F(2.0) * lg * min(max(q{k} - hi{k} - lbuf, F(0.0)), lcap)" for k in J],
        *step.lines,
        f"{i3}m = abs(d0)",
        *[f"{i3}m = max(m, abs(d{k}))" for k in range(1, n)],
        f"{i3}if m > max_joint:",
        f"{i4}sc = max_joint / m",
        *[f"{i4}d{k} = d{k} * sc" for k in J],
    ]
    for k in J:
        sim_src += [
            f"{i3}q{k} = q{k} + d{k}",
            f"{i3}if q{k} < lo{k}:",
            f"{i4}q{k} = lo{k}",
            f"{i3}elif q{k} > hi{k}:",
            f"{i4}q{k} = hi{k}",
        ]
    return "\n".join(head + fk_src + sim_src) + "\n"


def source_digest(src: str) -> str:
    """sha256 (hex) of generated source: names the cached module and is checked before its import."""
    return hashlib.sha256(src.encode()).hexdigest()


# --------------------------------------------------------------------------- cache + import
_lock = threading.Lock()
_loaded: dict[str, object] = {}
_warned: set[str] = set()
# what numba (pickle, the import system, the file system) raises on a corrupt or unreadable
# cache file; a numba TypingError/LoweringError (a bug in the generated code) is not among them
_CACHE_ERRORS = (pickle.UnpicklingError, EOFError, ValueError, TypeError, KeyError, IndexError,
                 AttributeError, ImportError, OSError)


class KernelCacheWarning(RuntimeWarning):
    """The kernel cache could not be used: the kernel was compiled in memory, without caching."""


def cache_dir() -> Path:
    """Directory holding generated kernel modules and numba's cache of them (not created here).

    ``$CAMO_SBI_KERNEL_CACHE``, else ``$XDG_CACHE_HOME/camo_sbi/kernels``, else
    ``~/.cache/camo_sbi/kernels``. There is no fallback: see `check_cache_dir`.
    """
    env = os.environ.get("CAMO_SBI_KERNEL_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "camo_sbi" / "kernels"


def check_cache_dir(path: str | os.PathLike) -> str | None:
    """Why ``path`` must not hold kernel code, or None when it is a private directory of this user.

    numba unpickles what it finds in the cache, so the directory (and its ``__pycache__``) must
    be a real directory (not a symbolic link), owned by the current user and writable by no one
    else (group/other write bits clear): `camo_sbi._io.check_private_dir`.
    """
    return check_private_dir(path)


def _private_cache_dir() -> tuple[Path, str | None]:
    """The cache directory, created with mode 0700 if missing, and why it is unusable (or None)."""
    d = cache_dir()
    return d, make_private_dir(d)


def _warn_once(message: str) -> None:
    if message not in _warned:
        _warned.add(message)
        warnings.warn(message, KernelCacheWarning, stacklevel=4)


def _write_once(path: Path, src: str) -> None:
    """Write ``src`` to ``path`` unless it already holds exactly that; then verify what is there.

    The file is imported afterwards, so it must hold the very source generated here: its
    sha256 is compared with the digest of ``src`` (ImportError otherwise, and the cache entry
    is rebuilt).
    """
    data = src.encode()
    if not (path.is_file() and path.read_bytes() == data):
        atomic_write_bytes(path, data)  # (unchanged files keep their mtime: numba's cache stays valid)
    if hashlib.sha256(path.read_bytes()).hexdigest() != source_digest(src):
        raise ImportError(f"{path}: content differs from the generated kernel source")


def _signatures(dtype) -> dict[str, tuple]:
    """The argument types `kernel_fk` / `kernel_simulate` call ``fk`` / ``simulate`` with."""
    from numba import types

    F = types.float32 if np.dtype(dtype) == np.float32 else types.float64
    a1 = lambda t: types.Array(t, 1, "C")  # noqa: E731
    a2, a3 = types.Array(F, 2, "C"), types.Array(F, 3, "C")
    i = types.int64
    return {"simulate": (i, i, a2, a2, a2, i, F, F, F, F, F, F, F, types.boolean, F, F, F, a3, a3, a1(i),
                         a1(types.boolean))}


def _import_file(name: str, path: Path, dtype):
    """Import the generated module at ``path`` and compile its kernels now (from numba's cache if valid).

    Compiling here rather than at the first call makes a corrupt cache file fail inside
    `load_kernel`, where it is rebuilt, instead of inside every later simulation.
    """
    mspec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(mspec)
    sys.modules[name] = mod
    try:
        with _in_tree_numba_cache():
            mspec.loader.exec_module(mod)
        for fn, sig in _signatures(dtype).items():
            getattr(mod, fn).compile(sig)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return mod


@contextlib.contextmanager
def _in_tree_numba_cache():
    """numba's cache of a generated module goes beside it (the checked private directory's
    ``__pycache__``), never to ``NUMBA_CACHE_DIR`` or a locator named by the environment, which
    `check_cache_dir` did not check. numba picks the location when a function is decorated."""
    from numba.core import config as numba_config

    saved = {k: getattr(numba_config, k) for k in ("CACHE_DIR", "CACHE_LOCATOR_CLASSES") if hasattr(numba_config, k)}
    try:
        for k in saved:
            setattr(numba_config, k, "")
        yield
    finally:
        for k, v in saved.items():
            setattr(numba_config, k, v)


def _remove_cached(d: Path, name: str) -> None:
    """Delete module ``name``'s generated source and numba's index/data files for it."""
    for p in [d / f"{name}.py", *(d / "__pycache__").glob(f"{name}.*")]:
        try:
            p.unlink()
        except FileNotFoundError:
            pass


def _load_cached(spec: ChainSpec, dtype):
    """The module from the private on-disk cache, or None (with a warning) when that is impossible.

    The cached file is named by the sha256 of its source and compared with it before import."""
    d, reason = _private_cache_dir()
    if reason is not None:
        _warn_once(f"kernel cache {d} {reason}; compiling kernels in memory without caching "
                   "(set CAMO_SBI_KERNEL_CACHE to a private directory)")
        return None
    src = generate_source(spec, dtype)
    name = f"camo_sbi_kernel_{source_digest(src)[:32]}"
    path = d / f"{name}.py"
    errors = []
    for _ in range(2):  # a corrupt cache file is deleted and the module rebuilt once
        try:
            _write_once(path, src)
            return _import_file(name, path, dtype)
        except _CACHE_ERRORS as exc:
            errors.append(f"{type(exc).__name__}: {exc}")
            _remove_cached(d, name)
    _warn_once(f"kernel cache {d}: {name} could not be loaded or rebuilt ({errors[-1]}); "
               "compiling it in memory without caching")
    return None


def _compile_in_memory(spec: ChainSpec, dtype, name: str):
    """The module compiled from a string (``cache=False``): nothing is read from or written to disk."""
    src = generate_source(spec, dtype, cache=False)
    filename = f"<camo_sbi kernel {name}>"
    linecache.cache[filename] = (len(src), None, src.splitlines(True), filename)  # readable tracebacks
    mod = types.ModuleType(name)
    mod.__file__ = filename
    exec(compile(src, filename, "exec"), mod.__dict__)  # noqa: S102 - our own generated source
    return mod


def load_kernel(spec: ChainSpec, dtype):
    """The imported generated module for (``spec``, ``dtype``): attributes ``fk`` and ``simulate``.

    Cached on disk in `cache_dir` when that is a private directory of this user
    (`check_cache_dir`); otherwise, or when its cache files cannot be loaded even after being
    rebuilt, compiled in memory with a `KernelCacheWarning`. Same machine code either way.
    """
    dt = _DTYPES[np.dtype(dtype)]
    key = hashlib.sha256(f"{GENERATOR_VERSION}|{spec.digest}|{dt}".encode()).hexdigest()[:24]
    announce_compiling()  # one line if this (or any camo_sbi kernel) compiles rather than loads
    with _lock:
        mod = _loaded.get(key)
        if mod is not None:
            return mod
        mod = _load_cached(spec, dtype)
        if mod is None:
            mod = _compile_in_memory(spec, dtype, f"camo_sbi_kernel_{key}")
        _loaded[key] = mod
        return mod


# --------------------------------------------------------------------------- numpy entry points
def kernel_fk(spec: ChainSpec, q: np.ndarray) -> np.ndarray:
    """q (B, n) float32/float64 -> end-effector positions (B, 3), same dtype."""
    q = np.ascontiguousarray(q)
    out = np.empty((q.shape[0], 3), dtype=q.dtype)
    _run(load_kernel(spec, q.dtype).fk, q.shape[0], q, out)
    return out


def kernel_simulate(spec: ChainSpec, theta: np.ndarray, goal: np.ndarray, start: np.ndarray, *,
                    max_steps: int, tol: float, gain: float, damping: float,
                    max_cartesian_step: float, max_joint_step: float, null_gain: float,
                    derivative_gain: float = 0.0, early_stop: bool = True, limit_gain: float = 0.0,
                    limit_buffer: float = 0.01, limit_cap: float = 0.2, out=None):
    """Run the controller: theta (B, 2n), goal (B, 3), start (B, n), all C-contiguous, one dtype.

    Returns (q (B, T, n), ee (B, T, 3), length (B,) int64, reached (B,) bool); ``out`` may
    supply these four arrays preallocated.
    """
    dtype = theta.dtype
    F = dtype.type
    B, n, T = theta.shape[0], spec.n_joints, int(max_steps)
    if out is None:
        out = (np.empty((B, T, n), dtype), np.empty((B, T, 3), dtype),
               np.empty(B, np.int64), np.empty(B, np.bool_))
    _run(load_kernel(spec, dtype).simulate, B,
         theta, goal, start, np.int64(T), F(tol), F(gain), F(damping * damping),
         F(max_cartesian_step), F(max_joint_step), F(null_gain), F(derivative_gain), bool(early_stop),
         F(limit_gain), F(limit_buffer), F(limit_cap), *out)
    return out


MIN_ROWS_PER_THREAD = 64
"""Batches smaller than this many rows per thread run in the calling thread alone."""


def _run(kernel, rows: int, *args) -> None:
    """kernel(c, n_chunks, *args) over contiguous row chunks on the shared thread runner.

    Every row is computed on its own, so the result does not depend on the number of chunks."""
    n_chunks = int(max(1, min(default_workers(), rows // MIN_ROWS_PER_THREAD)))
    run_chunks(kernel, n_chunks, *args)
