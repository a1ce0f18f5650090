"""What the console scripts share: --preset lookup before tyro parses, the entry-point wrapper (SIGTERM handling,
one-line errors, Ctrl-C) and the exception hook that prints gsmsdr's own errors without a traceback.

Errors of the classes in :data:`USER_ERRORS` are meant for the person running the command: their message names the
file or value and says what to do, so a traceback only hides it. They print as one line, in our CLIs and (through
:func:`install_excepthook`, which importing ``gsmsdr_ns.plugin`` runs) in ``ns-train``, ``ns-eval`` and
``ns-viewer``. ``GSMSDR_DEBUG=1`` in the environment brings the traceback back; other exceptions always keep it.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from gsmsdr_ns.io.errors import DiskFullError, InputError, SceneFolderMissingError, storage_error_line

USER_ERRORS = (InputError, DiskFullError)
"""Exception classes printed as one clean line (``<ClassName>: <message>``) instead of a traceback."""

DEBUG_ENV = "GSMSDR_DEBUG"
"""Environment variable: set to 1 to get the traceback of :data:`USER_ERRORS` too."""

INTERRUPT_EXIT_STATUS = 130
"""Exit status after Ctrl-C (128 + SIGINT), as shells report it."""

NOTHING_WRITTEN = "interrupted; nothing was written"
"""What the writers that build their output in a temporary path and rename it at the end print on Ctrl-C."""


def debug_tracebacks() -> bool:
    """True when ``GSMSDR_DEBUG`` asks for full tracebacks of our own errors."""
    return os.environ.get(DEBUG_ENV, "").strip().lower() not in ("", "0", "false", "no")


def user_error_message(exc: BaseException) -> str:
    """The message of an error of :data:`USER_ERRORS`, with the fix that exists for the running command."""
    if isinstance(exc, SceneFolderMissingError):
        return exc.for_command(Path(sys.argv[0]).name if sys.argv else "")
    return str(exc)


def user_error_line(exc: BaseException) -> str:
    """The one line an error of :data:`USER_ERRORS` prints as: ``InputError: gsmsdr: ...``."""
    name = "InputError" if isinstance(exc, SceneFolderMissingError) else type(exc).__name__  # as before it had a class
    return f"{name}: {user_error_message(exc)}"


def _print_user_errors(previous: Callable) -> Callable:
    def hook(exc_type, exc, tb) -> None:
        if not debug_tracebacks():
            if issubclass(exc_type, USER_ERRORS):
                print(user_error_line(exc), file=sys.stderr, flush=True)
                return
            storage = storage_error_line(exc) if exc is not None else None
            if storage is not None:  # a full disk or a refused write, whoever's code was writing
                print(storage, file=sys.stderr, flush=True)
                return
        previous(exc_type, exc, tb)

    hook.gsmsdr_user_errors = True  # type: ignore[attr-defined]  # marks the hook as installed (idempotence)
    return hook


def install_excepthook() -> None:
    """Make an uncaught error of :data:`USER_ERRORS` print as one line; every other exception goes to the hook that
    was installed before (the interpreter's traceback). Idempotent."""
    if not getattr(sys.excepthook, "gsmsdr_user_errors", False):
        sys.excepthook = _print_user_errors(sys.excepthook)


def preset_from_argv(argv: Sequence[str]) -> Path | None:
    """Find --preset before tyro parses, so the preset can become the defaults that flags override."""
    for i, arg in enumerate(argv):
        if arg == "--preset" and i + 1 < len(argv):
            return Path(argv[i + 1])
        if arg.startswith("--preset="):
            return Path(arg.split("=", 1)[1])
    return None


def _exit_on_sigterm(signum, _frame) -> None:
    # SystemExit unwinds through the writer's cleanup (generate_scene, degrade_scene), so a killed run leaves no
    # temp directory.
    raise SystemExit(128 + signum)


def run_entrypoint(parse: Callable[[], Any], console: Console, interrupted: str = NOTHING_WRITTEN) -> None:
    """Run ``parse().main()`` as a console script.

    SIGTERM exits through the cleanup code. Ctrl-C prints ``interrupted`` (one line: what was kept, if anything) and
    exits with status 130. An error of :data:`USER_ERRORS`, a FileExistsError, FileNotFoundError or ValueError, and
    any error caused by a full disk or a refused write (:func:`storage_error_line`), is printed as one red "error:"
    line with exit status 1 (with ``GSMSDR_DEBUG=1``: re-raised, with its traceback).
    """
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        parse().main()
    except KeyboardInterrupt:
        # The writers' cleanup has already run while the KeyboardInterrupt unwound to here.
        console.print(f"[bold red]{escape(interrupted)}[/bold red]", highlight=False, soft_wrap=True)
        sys.exit(INTERRUPT_EXIT_STATUS)
    except (*USER_ERRORS, FileExistsError, FileNotFoundError, ValueError) as e:
        if debug_tracebacks():
            raise
        message = user_error_message(e) if isinstance(e, USER_ERRORS) else str(e)
        console.print(f"[bold red]error:[/bold red] {escape(message)}", highlight=False, soft_wrap=True)
        sys.exit(1)
    except Exception as e:
        storage = storage_error_line(e)  # a full disk or a refused write, in our code or a library's
        if storage is None or debug_tracebacks():
            raise
        console.print(f"[bold red]error:[/bold red] {escape(storage)}", highlight=False, soft_wrap=True)
        sys.exit(1)
