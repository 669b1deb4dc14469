"""Pieces every ``posernet-*`` command shares: the entry point with its config check and error
policy, one-line user errors, the device and thread settings, logging.

Error policy (the same for every command): a user error (bad config value, missing or
malformed input, unwritable output, ``device=cuda`` without CUDA) is one line on stderr,
``posernet-<cmd>: error: <message>``, exit status 1; Ctrl-C is one line,
``posernet-<cmd>: interrupted`` (plus what can be resumed), exit status 130.
"""

from __future__ import annotations

import re
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from ..io import writable_dir, writable_file
from .validation import ConfigValueError, check_config

__all__ = [
    "check_config",
    "interrupted",
    "quiet_lightning",
    "quote_list_args",
    "report_error",
    "resolve_device",
    "run_app",
    "run_task",
    "set_threads",
    "user_errors",
    "writable_dir",
    "writable_file",
]

T = TypeVar("T")

EXIT_USER_ERROR = 1
EXIT_INTERRUPTED = 130

_sigint_seen = False  # set by our SIGINT handler: a Ctrl-C happened in this process


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions caused by the user's inputs: reported in one line, no traceback."""
    from hydra.errors import InstantiationException
    from omegaconf.errors import MissingMandatoryValue

    from ..checkpoints import CheckpointError
    from ..graph import GraphValidationError

    return (ConfigValueError, FileNotFoundError, NotADirectoryError,
            GraphValidationError, CheckpointError, MissingMandatoryValue, InstantiationException)


def _one_line(message: str) -> str:
    """A (possibly multi-line) message as one line, without OmegaConf's key/type trailer."""
    lines = [ln.strip() for ln in message.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith(("full_key:", "object_type=",
                                                               "reference_type="))]
    return " ".join(lines)


def report_error(prog: str, exc: BaseException) -> None:
    """Print ``prog: error: message`` (one line) to stderr; for a failed instantiation: its
    root cause."""
    from hydra.errors import InstantiationException

    while isinstance(exc, InstantiationException) and exc.__cause__ is not None:
        exc = exc.__cause__
    print(f"{prog}: error: {_one_line(str(exc)) or type(exc).__name__}", file=sys.stderr)


def interrupted(prog: str, hint: str | None = None) -> NoReturn:
    """Ctrl-C: one line (with what can be resumed), exit status 130."""
    lead = "\n" if sys.stderr.isatty() else ""  # after the terminal's ^C (or a progress bar)
    print(f"{lead}{prog}: interrupted" + (f"; {hint}" if hint else ""), file=sys.stderr)
    raise SystemExit(EXIT_INTERRUPTED)


def run_task(prog: str, task: Callable[[Any], T], cfg: Any, *,
             errors: tuple[type[BaseException], ...] = (),
             resume_hint: Callable[[Any], str | None] | None = None) -> T:
    """``task(cfg)`` under the commands' error policy: a user error (:func:`user_errors` or
    ``errors``) -> one line and ``SystemExit(1)``; Ctrl-C -> one line and ``SystemExit(130)``.

    ``resume_hint(cfg)`` says what an interrupted run left that can be resumed (or None).
    """

    def hint() -> str | None:
        try:
            return resume_hint(cfg) if resume_hint is not None else None
        except Exception:  # a hint never hides the interruption
            return None

    try:
        return task(cfg)
    except KeyboardInterrupt:
        interrupted(prog, hint())
    except SystemExit as exc:
        # Lightning turns Ctrl-C into its own sys.exit(1) after a graceful shutdown
        if _sigint_seen and exc.code not in (0, None, EXIT_INTERRUPTED):
            interrupted(prog, hint())
        raise
    except (*user_errors(), *errors) as exc:
        report_error(prog, exc)
        _discard_empty_run_dir()
        raise SystemExit(EXIT_USER_ERROR) from None


def _discard_empty_run_dir() -> None:
    """After a user error inside a Hydra job: remove the run folder Hydra made for it when it
    holds nothing but Hydra's own files (its log, ``.hydra/``), so a bad input leaves nothing
    behind. A folder with anything else in it (outputs, a resumed run) is kept."""
    import shutil

    try:
        from hydra.core.hydra_config import HydraConfig

        run_dir = Path(HydraConfig.get().runtime.output_dir)
    except Exception:  # not inside a Hydra job
        return
    if not run_dir.is_dir() or run_dir.resolve() == Path.cwd().resolve():
        return
    entries = list(run_dir.iterdir())
    if all(p.name == ".hydra" or p.suffix == ".log" for p in entries):
        shutil.rmtree(run_dir, ignore_errors=True)


def _on_sigint(signum: int, frame: Any) -> None:
    global _sigint_seen
    _sigint_seen = True
    raise KeyboardInterrupt


_final_collection_skipped = False


def _skip_final_collection() -> None:
    """At interpreter exit, move every object into the garbage collector's permanent
    generation (``gc.freeze``), so that Python's final cyclic collections skip them. Those
    collections walk every object torch, OpenCV, SciPy and Hydra created and cost 0.3-0.45 s
    of a few-second command, when everything is written and closed and the operating system
    frees the memory anyway. Exit handlers still run (logging's flush, temporary folders) and
    objects still go by reference counting; only reference cycles are left to the operating
    system. Registered with ``atexit``, so it acts only when the process ends, never in a
    caller's process that keeps running (a test calling ``main``)."""
    global _final_collection_skipped
    if not _final_collection_skipped:
        import atexit
        import gc

        atexit.register(gc.freeze)
        _final_collection_skipped = True


def run_app(prog: str, config_name: str, app: Callable[[], Any], *,
            list_args: tuple[str, ...] = (),
            direct: Callable[[Any], Any] | None = None) -> None:
    """Console entry point of a command: check the config (before Hydra makes a run folder),
    then run the Hydra ``app``; Ctrl-C anywhere is one line and exit status 130.

    ``direct(cfg)``: for a command whose Hydra job makes no run folder, changes no directory
    and configures no logging (``posernet-reconstruct``), a plain run (not ``--help``, ``-m``,
    ...) calls it with the config the check already composed instead of letting ``app``
    compose it twice more (about 0.3 s of a few-second run)."""
    from ..startup import interrupted_while_starting

    if signal.getsignal(signal.SIGINT) in (signal.default_int_handler,
                                           interrupted_while_starting):
        signal.signal(signal.SIGINT, _on_sigint)
    _skip_final_collection()
    if any(a in ("--help", "-h") for a in sys.argv[1:]):
        from . import CONFIG_DIR
        from .help import command_help

        print(command_help(prog, CONFIG_DIR, config_name), end="")
        raise SystemExit(0)
    try:
        if list_args:
            sys.argv = quote_list_args(sys.argv, list_args)
        cfg = preflight(prog, config_name)
        if direct is not None and cfg is not None:
            direct(cfg)
        else:
            app()
    except KeyboardInterrupt:
        interrupted(prog)


def preflight(prog: str, config_name: str, argv: list[str] | None = None) -> Any:
    """Compose the config from the command line as Hydra will and :func:`check_config` it, so
    that a bad value, an unknown key or group option, or an unwritable output is one line
    before Hydra creates a run folder. Skipped for Hydra's own modes (``--help``, ``--cfg``,
    ``-m``, another config dir, ...): the command checks its config again when it starts.
    Returns the checked config without its ``hydra`` node (what a Hydra task receives), or
    None when skipped."""
    from hydra._internal.utils import get_args_parser

    try:
        args = get_args_parser().parse_args(sys.argv[1:] if argv is None else argv)
    except SystemExit:  # Hydra reports its own usage errors
        return None
    if (args.help or args.hydra_help or args.cfg or args.info or args.shell_completion
            or args.multirun or args.config_path or args.config_name or args.config_dir
            or args.experimental_rerun or args.run):
        return None
    from . import CONFIG_DIR

    for ov in args.overrides:  # "+foo=1": a new top-level key nothing reads
        key = ov.split("=", 1)[0]
        if key.startswith("+") and "." not in key and "@" not in key and \
                not (Path(CONFIG_DIR) / key.lstrip("+")).is_dir():
            print(f"{prog}: error: {key.lstrip('+')}: no such option of {prog} "
                  f"(see {prog} --help)", file=sys.stderr)
            raise SystemExit(EXIT_USER_ERROR)
    from hydra import compose, initialize_config_dir
    from hydra.core.hydra_config import HydraConfig
    from hydra.errors import HydraException
    from hydra.types import RunMode
    from omegaconf import open_dict, read_write
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3",
                                   job_name=config_name):
            cfg = compose(config_name, overrides=list(args.overrides), return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as exc:
        print(f"{prog}: error: {hydra_error_message(exc, config_name)}", file=sys.stderr)
        raise SystemExit(EXIT_USER_ERROR) from None
    if cfg.hydra.get("mode") == RunMode.MULTIRUN:  # e.g. +experiment=depth_sweep
        return None
    run_dir = Path(str(cfg.hydra.run.dir)).absolute()
    with read_write(cfg.hydra), open_dict(cfg.hydra):
        cfg.hydra.runtime.output_dir = str(run_dir)
    hydra_config = HydraConfig.instance()
    before = hydra_config.cfg
    hydra_config.set_config(cfg)  # ${hydra:runtime.output_dir} resolves as in the run
    try:
        if run_dir != Path.cwd().absolute():
            writable_dir(cfg.hydra.run.dir, "hydra.run.dir")
        check_config(cfg, config_name)
    except (*user_errors(), ValueError) as exc:
        report_error(prog, exc)
        raise SystemExit(EXIT_USER_ERROR) from None
    finally:
        hydra_config.cfg = before
    with read_write(cfg), open_dict(cfg):
        del cfg["hydra"]
    return cfg


#: what an unknown key usually meant, by (config name, key)
_KEY_HINTS = {("train", "device"): "the trainer picks it: trainer=gpu or trainer.accelerator=..."}


def hydra_error_message(exc: BaseException, config_name: str = "") -> str:
    """Hydra's composition errors (unknown key or group option, bad override syntax) in one
    line, in the ``key: value is not ...`` form where it applies."""
    from hydra.errors import MissingConfigException

    msg = str(exc)
    if isinstance(exc, MissingConfigException):
        found = re.search(r"Could not find '(.+)/([^/']+)'", msg)
        options = re.findall(r"^\t(\S+)$", msg.split("Config search path")[0], re.M)
        if found and options:
            return (f"{found.group(1).replace('/', '.')}: {found.group(2)!r} is not one of "
                    f"{', '.join(options)}")
    override = re.match(r"Could not override '([^']+)'", msg)
    if override and "not in struct" in str(exc.__cause__):
        key = override.group(1)
        hint = _KEY_HINTS.get((config_name, key))
        return f"{key}: no such key in this command's config" + (f" ({hint})" if hint else "")
    cause = exc.__cause__
    if cause is not None and str(cause) and str(cause) not in msg:
        msg = f"{msg}: {cause}"
    return _one_line(msg)


def resolve_device(name: Any) -> str:
    """``auto`` -> ``cuda`` when available, else ``cpu``; other names as given (checked by
    :func:`check_config`)."""
    name = str(name)
    if name == "auto":
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def quiet_lightning() -> None:
    """Avoid doubled log lines and known-harmless warnings under Hydra's logging setup.

    ``import lightning`` always adds its own console handler; when Hydra has configured the
    root logger the same messages would be printed twice, so that handler is dropped.
    """
    import logging
    import warnings

    if logging.getLogger().hasHandlers():
        lg = logging.getLogger("lightning")
        for h in list(lg.handlers):
            if type(h) is logging.StreamHandler:
                lg.removeHandler(h)
    warnings.filterwarnings("ignore", message=r".*treespec, LeafSpec.*")


def set_threads(n: int | None) -> None:
    """``torch.set_num_threads(n)`` when ``n`` is set (tiny graphs run fastest on one thread)."""
    if n:
        import torch

        torch.set_num_threads(int(n))


def quote_list_args(argv: list[str], keys: tuple[str, ...]) -> list[str]:
    """``key=a,b,c`` for ``key`` in ``keys`` would read as a Hydra sweep: pass it as one quoted
    string instead (``intrinsics=585,585,320,240`` is what users type)."""
    pattern = re.compile(rf"^({'|'.join(map(re.escape, keys))})=([^'\"\[].*,.*)$")
    return [pattern.sub(r"\1='\2'", a) for a in argv]
