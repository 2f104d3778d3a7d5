"""The `camo-sbi` command line: infer joint limits from reaching trajectories and compare methods.

Conventions every command follows:

* ``--help`` shows each option's default, the registered method names and subject profiles
  where the command takes them, and ends with examples; ``camo-sbi --version``;
  ``python -m camo_sbi`` is ``camo-sbi``.
* ``-v`` / ``-vv`` (notes, debug), ``-q`` (errors only: no warnings, no progress bars),
  ``--log-level LEVEL``. Warnings (a method's fallback, a damaged cell) and notes go through
  `logging` to stderr with ``tqdm.write``, one line each, above the progress bar, never into it.
* ``--json``: a JSON summary on stdout when the command ends (paths written, statuses, headline
  numbers; `camo_sbi.experiments.summary`); the usual output then goes to stderr.
* Bad input exits 2 with one line ``camo-sbi: error: ...`` naming the flag, file or row.

The parser is built from modules that import nothing heavy: numpy, torch, pandas, matplotlib,
scipy, numba, pybullet, pyabc and sbi are imported by the commands that need them, so
``--help`` returns without them (``tests/test_cli.py`` checks which modules it imports).

`console_main` is the console entry point (``camo-sbi``, ``python -m camo_sbi``): it alone
installs the signal handling (SIGTERM exits 143, Ctrl-C 130, both with "finished cells are
saved"). `main` is the in-process call (tests, notebooks): it installs no signal handler, and a
KeyboardInterrupt propagates, so a SIGTERM or Ctrl-C sent to the calling process (a test run)
stops that process instead of being taken for the command's own.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import logging
import os
import shutil
import signal
import sys
import textwrap
import time
import warnings
from typing import NamedTuple

from camo_sbi import __version__

__all__ = ["COMMANDS", "Terminated", "build_parser", "console_main", "main"]

_RESUME = "finished cells are saved; re-run the same command to resume"
LOGGER = "camo_sbi"
_LEVELS = ("debug", "info", "warning", "error")
CLI_OPTIONS = ("verbose", "quiet", "log_level", "json")
"""The destinations of the options every command shares; removed before a command runs (they
change what is printed, never a result, so they are not settings of a run's manifest)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, SLURM), raised in the main thread and handled like Ctrl-C."""


REDELIVER_DELAY = 0.02
"""Seconds after which a signal whose exception Python dropped (`_signals_as_exceptions`) is sent again."""


# ----------------------------------------------------------------------------- help


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option's default in its help line (as argparse's ArgumentDefaultsHelpFormatter,
    also for options without a help text); descriptions and epilogs keep their line breaks."""

    def _get_help_string(self, action):
        text = action.help or ""
        if _shows_default(action) and "%(default)" not in text and "default" not in text.lower():
            text = f"{text} (default: %(default)s)" if text else "default: %(default)s"
        return text

    def _split_lines(self, text, width):  # never break "abc-smc" or "--test-goals" at the hyphen
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False, break_long_words=False)

    def _format_action(self, action):
        if not action.help and _shows_default(action):
            action = copy.copy(action)
            action.help = "default: %(default)s"
        return super()._format_action(action)


def _shows_default(action) -> bool:
    """An option with a value whose default says something (not a flag, None or an empty list)."""
    default = action.default
    return (bool(action.option_strings) and action.nargs != 0 and default is not None
            and default is not argparse.SUPPRESS and default != [])


def _wrap(text: str, indent: str = "  ") -> str:
    width = max(60, min(100, shutil.get_terminal_size((100, 24)).columns)) - 2
    return textwrap.fill(text, width, initial_indent=indent, subsequent_indent=indent + "  " if indent else "")


def _methods_text() -> str:
    from camo_sbi.inference.registry import get_method, names

    rows = [f"{n}: {get_method(n).description}" for n in names()]
    base = ", ".join(names(baseline=True))
    return ("methods (registered; the baselines " + base + " are added to every comparison):\n"
            + "\n".join(_wrap(r) for r in rows))


def _subjects_text() -> str:
    from camo_sbi.simulators.registry import get_model, model_names

    return ("subject profiles (--subjects; a --urdf model's subject is its --limits file):\n"
            + "\n".join(_wrap(f"{m}: {', '.join(get_model(m).subjects())}") for m in model_names()))


def _impairments_text() -> str:
    from camo_sbi.simulators.registry import subject_names

    return "impairment profiles of the person (--subject):\n" + _wrap(", ".join(subject_names("human")))


def _examples(*lines: str) -> str:
    return "examples:\n" + "\n".join(f"  {line}" for line in lines)


class Command(NamedTuple):
    """A subcommand: its one-line help, where its options and function come from, what its
    ``--help`` lists ("methods", "subjects", "human"), and its examples."""

    name: str
    help: str
    arguments: str  # "module:function" under camo_sbi.experiments, or a function of this module
    func: str
    lists: tuple[str, ...]
    examples: tuple[str, ...]


_TINY = "camo-sbi compare --model panda --methods camo,naive --budgets 200 --seeds 1 --tasks 2 --out runs/tiny"
_OBS = "--urdf tests/data/arm7.urdf --ee tool --start 0,0.4,0,-1.1,0,0.7,0"

COMMANDS = (
    Command("compare", "compare inference methods on a grid (resumable)", "compare:add_arguments",
            "compare:main", ("methods", "subjects"),
            (_TINY, "camo-sbi compare --model human --methods camo,camo-hull,abc-smc,npe --budgets 500,2000 "
                    "--seeds 3 --tasks 5 --workers 2 --out runs/human")),
    Command("reference", "build (or verify) reference posteriors of a fixed benchmark set of observations",
            "reference:add_arguments", "reference:main", ("subjects",),
            ("camo-sbi reference --model panda --setting informative --observations 10 --out refs/panda-informative",
             "camo-sbi compare --reference refs/panda-informative --methods camo-seq,npe,exact-likelihood "
             "--budgets 1000,10000 --out runs/vs-reference")),
    Command("run", "run a whole comparison described in a study file (TOML)", "run:add_arguments",
            "run:main", ("methods", "subjects"),
            ("camo-sbi run study.toml", "camo-sbi run docs/study_example.toml --json")),
    Command("calibrate", "coverage and SBC of each method over synthetic subjects", "calibrate:add_arguments",
            "calibrate:main", ("methods",),
            ("camo-sbi calibrate --model panda --methods camo,naive --subjects 20 --out runs/calibrate",)),
    Command("amortize", "train an amortized estimator (npe-amortized) once per body model",
            "amortize:add_arguments", "amortize:main", (),
            ("camo-sbi amortize --model panda --simulations 200000 --out panda.pt",
             "camo-sbi amortize --model panda --fast --threads 2 --out panda-fast.pt")),
    Command("report", "write a self-contained HTML report of a run directory", "report:add_arguments",
            "report:main", (), ("camo-sbi report runs/tiny", "camo-sbi report runs/tiny -o tiny.html")),
    Command("demo", "simulate a batch of reaches and plot them", "cli:_demo_arguments", "demo:main", (),
            ("camo-sbi demo --model human --out demo.png",)),
    Command("describe", "describe a body model: joints, axes, signs, ranges, frames, and a figure",
            "describe:add_arguments", "describe:main", (),
            ("camo-sbi describe --model human --out runs/describe",
             "camo-sbi describe --urdf tests/data/arm7.urdf --ee tool --out runs/describe")),
    Command("simulate-observations", "write synthetic recorded reaches of a subject (recording format)",
            "simulate:add_arguments", "simulate:main", (),
            (f"camo-sbi simulate-observations {_OBS} --limits tests/data/arm7_limits.json --reaches 5 "
             "--seed 0 --noise-joint-deg 1 --noise-ee-mm 5 --out obs.csv",)),
    Command("infer", "infer joint limits from recorded reaches", "infer:add_arguments",
            "infer:main", ("methods",),
            (f"camo-sbi infer --observations obs.csv {_OBS} --noise-joint-deg 1 --noise-ee-mm 5 "
             "--methods camo,naive,nominal,npe --budget 1000 --seed 0 --out inferred",)),
    Command("robustness", "every method under observation noise, a faster recorder and a mis-sized model",
            "robustness:add_arguments", "robustness:main", ("methods", "subjects"),
            ("camo-sbi robustness --model panda --methods camo-js,naive --seeds 2 --out runs/robustness",)),
    Command("warmup", "compile the numba kernels now, once per user (a first run would compile them)",
            "warmup:add_arguments", "warmup:main", (),
            ("camo-sbi warmup", "camo-sbi warmup --models panda,human")),
    Command("render-scene", "render the block-stacking scene to a PNG", "render_scene:add_arguments",
            "render_scene:main", ("human",), ("camo-sbi render-scene --subject frozen_shoulder --out scene.png",)),
)
REPRODUCE = (
    Command("panda", "manipulator experiment (paper Fig. 2-3); --model human also works",
            "reproduce_panda:add_arguments", "reproduce_panda:main", ("methods", "subjects"),
            ("camo-sbi reproduce panda --setting paper --runs 30 --out runs/paper",
             "camo-sbi reproduce panda --runs 5 --tasks 5 --out runs/toolkit")),
    Command("hrc", "human-robot block stacking (paper Fig. 5)", "reproduce_hrc:add_arguments", "reproduce_hrc:main", ("human",),
            ("camo-sbi reproduce hrc --runs 10 --out runs/hrc",
             "camo-sbi reproduce hrc --runs 10 --observe carry --fix-torso --out runs/hrc-carry")),
)


def _resolve(ref: str):
    """``"module:name"`` of camo_sbi.experiments (``cli:...`` is this module)."""
    import importlib

    module, name = ref.split(":")
    mod = sys.modules[__name__] if module == "cli" else importlib.import_module(f"camo_sbi.experiments.{module}")
    return getattr(mod, name)


def _run_command(ref: str):
    """The command function, imported when the command runs (not when the parser is built)."""

    def run(args):
        return _resolve(ref)(args)

    return run


def _common_options(top: bool) -> argparse.ArgumentParser:
    """-v/-q/--log-level/--json, on the top parser and on every command (either place works)."""
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("output")
    unset = {} if top else {"default": argparse.SUPPRESS}
    g.add_argument("-v", "--verbose", action="count", help="show notes (-vv: debug messages too)",
                   **({"default": 0} if top else unset))
    g.add_argument("-q", "--quiet", action="count", help="errors only: no warnings, notes or progress bars",
                   **({"default": 0} if top else unset))
    g.add_argument("--log-level", choices=_LEVELS, type=str.lower, help="message level (overrides -v/-q)",
                   **({"default": None} if top else unset))
    g.add_argument("--json", action="store_true",
                   help="print a JSON summary on stdout at the end (paths written, statuses, headline "
                        "numbers); the usual output goes to stderr", **({"default": False} if top else unset))
    return p


def _epilog(command: Command) -> str:
    parts = []
    if "methods" in command.lists:
        parts.append(_methods_text())
    if "subjects" in command.lists:
        parts.append(_subjects_text())
    if "human" in command.lists:
        parts.append(_impairments_text())
    parts.append(_examples(*command.examples))
    return "\n\n".join(parts)


def _add_command(sub, command: Command, common) -> None:
    p = sub.add_parser(command.name, help=command.help, description=command.help[0].upper() + command.help[1:] + ".",
                       epilog=_epilog(command), formatter_class=HelpFormatter, parents=[common])
    _resolve(command.arguments)(p)
    p.set_defaults(func=_run_command(command.func))


def build_parser() -> argparse.ArgumentParser:
    common = _common_options(top=False)
    parser = argparse.ArgumentParser(
        prog="camo-sbi", formatter_class=HelpFormatter, parents=[_common_options(top=True)],
        description=_wrap("Infer a person's (or robot's) joint limits from observed reaching trajectories, "
                          "and compare inference methods on that problem, with the trivial answers next to "
                          "them. `camo-sbi COMMAND --help` shows a command's options, defaults and examples.",
                          indent=""),
        epilog="\n\n".join([_methods_text(), _subjects_text(),
                            _examples("camo-sbi compare --seeds 1 --tasks 2 --out runs/quickstart", _TINY,
                                      "camo-sbi run study.toml")]))
    parser.add_argument("--version", action="version", version=f"camo-sbi {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    rep = sub.add_parser("reproduce", help="reproduce the paper's experiments (panda, hrc)",
                         description="Reproduce the paper's experiments.", formatter_class=HelpFormatter,
                         parents=[common],
                         epilog=_examples(*REPRODUCE[0].examples[:1], *REPRODUCE[1].examples[:1]))
    rsub = rep.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    for command in REPRODUCE:
        _add_command(rsub, command, common)
    for command in COMMANDS:
        _add_command(sub, command, common)
    return parser


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    from camo_sbi.experiments.figure_options import add_figure_format_argument
    from camo_sbi.experiments.models import add_model_arguments

    add_model_arguments(p, limits=False)
    p.add_argument("--batch", type=int, default=64, help="reaches simulated")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/demo", help="a .png path, or a directory for demo.png")
    add_figure_format_argument(p)


# ----------------------------------------------------------------------------- messages


class _BarSafeHandler(logging.Handler):
    """Writes each record with ``tqdm.write`` (above a running progress bar, never into its line)."""

    def __init__(self, stream):
        super().__init__()
        self.stream = stream

    def emit(self, record):
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # a broken stream must not end the command
            self.handleError(record)


class _Formatter(logging.Formatter):
    def format(self, record):
        msg = record.getMessage()
        if record.levelno >= logging.WARNING:
            return f"camo-sbi: {record.levelname.lower()}: {msg}"
        if record.levelno <= logging.DEBUG:
            return f"camo-sbi: debug: [{record.name}] {msg}"
        return f"camo-sbi: {msg}"


def _level(args) -> int:
    if args.log_level:
        return getattr(logging, args.log_level.upper())
    if args.quiet:
        return logging.ERROR
    return {0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)


@contextlib.contextmanager
def _messages(level: int, stream):
    """camo_sbi's loggers and every warning, one line each, through logging and ``tqdm.write``.

    A warning becomes ``camo-sbi: warning: MESSAGE`` (camo_sbi's own: its category or the code
    that warned is camo_sbi's, e.g. a method's fallback status) or ``camo-sbi: warning: Category:
    MESSAGE`` (another library's; with -vv its source location too), at the WARNING level, so -q
    hides it. Python's filters still decide which warnings are shown and how
    often. Restored when the command ends (an in-process call leaves nothing behind).
    """
    logger = logging.getLogger(LOGGER)
    handler = _BarSafeHandler(stream)
    handler.setFormatter(_Formatter())
    old_level, old_propagate = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    original = warnings.showwarning

    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def show(message, category, filename, lineno, file=None, line=None):
        ours = category.__module__.startswith("camo_sbi") or os.path.abspath(filename).startswith(package + os.sep)
        text = str(message) if ours else f"{category.__name__}: {message}"
        if not ours and level <= logging.DEBUG:
            text += f" ({filename}:{lineno})"
        logging.getLogger(f"{LOGGER}.warnings").warning(text)

    warnings.showwarning = show
    try:
        yield logger
    finally:
        warnings.showwarning = original
        logger.removeHandler(handler)
        logger.setLevel(old_level)
        logger.propagate = old_propagate


@contextlib.contextmanager
def _progress_bars(enabled: bool):
    """With -q, every tqdm bar the command opens is disabled (tqdm reads its TQDM_* environment
    only when imported, so the flag is passed to each bar instead)."""
    if enabled:
        yield
        return
    from tqdm import std

    init = std.tqdm.__init__

    def quiet_init(self, *args, **kwargs):
        kwargs["disable"] = True
        init(self, *args, **kwargs)

    std.tqdm.__init__ = quiet_init
    try:
        yield
    finally:
        std.tqdm.__init__ = init


def _agg_backend() -> None:
    """Figures go to files: Agg, unless MPLBACKEND says otherwise (a library import never switches)."""
    if "MPLBACKEND" in os.environ:
        return
    if "matplotlib" in sys.modules:
        import matplotlib

        matplotlib.use("Agg")
    else:
        os.environ["MPLBACKEND"] = "Agg"


# ----------------------------------------------------------------------------- entry points


def os_error_line(exc: OSError) -> str:
    """One line for an OS-level failure, naming the path: ``PATH: No space left on device (ENOSPC)``."""
    import errno as _errno

    name = _errno.errorcode.get(exc.errno or 0)
    reason = exc.strerror or str(exc) or type(exc).__name__
    what = f"{reason} ({name})" if name else reason
    paths = [p for p in (exc.filename, getattr(exc, "filename2", None)) if p is not None]
    where = " -> ".join(str(os.fsdecode(p)) for p in paths)
    return f"{where}: {what}" if where else f"{type(exc).__name__}: {what}"


def _command_name(args) -> str:
    return " ".join(x for x in (args.command, getattr(args, "experiment", None)) if x)


def main(argv: list[str] | None = None) -> int:
    """Run ``camo-sbi ARGV`` in this process; returns the exit code (bad input: SystemExit(2)).

    Installs no signal handler: a KeyboardInterrupt (Ctrl-C, or SIGTERM under `console_main`)
    propagates to the caller.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    options = {k: getattr(args, k) for k in CLI_OPTIONS}
    command_args = argparse.Namespace(**{k: v for k, v in vars(args).items() if k not in CLI_OPTIONS})
    name = _command_name(args)
    _agg_backend()
    level = _level(args)
    stdout = sys.stdout
    t0 = time.time()
    code, error = 0, None
    with contextlib.ExitStack() as stack:
        if options["json"]:
            stack.enter_context(contextlib.redirect_stdout(sys.stderr))
        stack.enter_context(_messages(level, sys.stderr))
        stack.enter_context(_progress_bars(level < logging.ERROR))
        try:
            code = int(args.func(command_args) or 0)
        except ValueError as exc:
            code, error = 2, " ".join(str(exc).splitlines())  # one line, whatever a library put in it
        except OSError as exc:  # a full disk, a read-only or forbidden path, a file gone: one line, no traceback
            code, error = 2, os_error_line(exc)
    if options["json"]:
        from camo_sbi.experiments.summary import print_summary

        print_summary(name, command_args, code, error, started=t0, file=stdout)
    if error is not None:
        parser.exit(2, f"camo-sbi: error: {error}\n")
    return code


@contextlib.contextmanager
def _signals_as_exceptions():
    """SIGTERM raises `Terminated` once (later ones are ignored while cleaning up), Ctrl-C raises
    KeyboardInterrupt (Python's default, kept unless SIGINT was inherited as ignored); both are
    recorded in the yielded state.

    Python runs a signal's handler at the next instruction of the main thread, which can be a
    weakref callback or a finalizer that a library's C code triggers (seen: h5py writing a
    posterior's netCDF file); an exception raised there is "unraisable", printed and dropped,
    and the command ran on to its end. The unraisable hook here sends such a signal again to
    the main thread, from a helper thread after `REDELIVER_DELAY` seconds (sent from the hook
    itself it would be raised, and dropped, inside the hook), so it is raised at the command's
    next instruction. `console_main` also exits 143/130 if a library caught the exception
    outright.
    """
    import _thread

    state = {"terminated": False, "interrupted": False}
    closed = []  # set when the command has ended: a signal sent again after that would hit the caller

    def on_sigterm(signum, frame):
        if not state["terminated"]:
            state["terminated"] = True
            raise Terminated()

    def on_sigint(signum, frame):
        state["interrupted"] = True
        raise KeyboardInterrupt

    main_thread = _thread.get_ident()

    def send_again(sig):
        time.sleep(REDELIVER_DELAY)
        if not closed:
            signal.pthread_kill(main_thread, sig)  # a real signal: it also ends a sleep or a wait

    def on_unraisable(unraisable):
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            return previous_hook(unraisable)
        if isinstance(unraisable.exc_value, Terminated):
            state["terminated"] = False  # so that the SIGTERM sent again raises again
        # a bare thread: threading.Thread.start would wait for it, and the signal could come
        # back while this hook still runs
        _thread.start_new_thread(send_again, (signal.SIGTERM if isinstance(unraisable.exc_value, Terminated)
                                              else signal.SIGINT,))
        return None

    try:
        previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, on_sigterm)}
    except ValueError:  # not the main thread: leave the signals alone
        yield state
        return
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, on_sigint)
    previous_hook, sys.unraisablehook = sys.unraisablehook, on_unraisable
    try:
        yield state
    finally:
        closed.append(True)
        sys.unraisablehook = previous_hook
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def console_main(argv: list[str] | None = None) -> int:
    """The console entry point (``camo-sbi``, ``python -m camo_sbi``): `main` with SIGTERM and
    Ctrl-C turned into exit codes 143 and 130 ("finished cells are saved").

    A signal whose exception a library caught (and then let the command run to its end) still
    gives 143/130, with a line saying so: the exit status never hides that the run was stopped
    from outside. One dropped as unraisable is raised again (`_signals_as_exceptions`)."""
    with _signals_as_exceptions() as state:
        try:
            code = main(argv)
        except KeyboardInterrupt as exc:
            terminated = isinstance(exc, Terminated) or state["terminated"]
            print(f"{'terminated' if terminated else 'interrupted'}: {_RESUME}", file=sys.stderr)
            return 143 if terminated else 130
        except Exception:
            if not state["terminated"]:
                raise
            # SIGTERM sent to the whole process group (timeout, SLURM) can break the worker pool
            # before the parent's own handler runs: still a termination, not a crash
            print(f"terminated: {_RESUME}", file=sys.stderr)
            return 143
        if state["terminated"] or state["interrupted"]:
            what = "terminated" if state["terminated"] else "interrupted"
            print(f"{what}: the signal was caught inside the command, which ran to its end (exit code "
                  f"{code} without it); {_RESUME}", file=sys.stderr)
            return 143 if state["terminated"] else 130
        return code


if __name__ == "__main__":
    sys.exit(console_main())
