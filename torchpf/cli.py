"""What every command line of the project shares: ``--threads``, ``--debug``, output checks, one-line errors.

``python -m torchpf ...`` and ``python -m training ...`` run their commands through :func:`run_command`:

* bad input ends with one line ``PROG COMMAND: error: MESSAGE`` on stderr and exit status 2 (the loaders
  raise ValueError/OSError naming the file; an unreadable file, an overflow, an allocation that fails, an
  OpenCV parse error end the same way), Ctrl-C with ``PROG COMMAND: interrupted`` and status 130;
* ``--debug`` (or the environment variable ``TORCHPF_DEBUG=1``) shows the traceback instead;
* ``--threads N`` sets torch's intra-op threads; the default is the cores this process may run on
  (``len(os.sched_getaffinity(0))``), or 1 when the environment variable ``CI`` is set (shared runners,
  where torch's own default of every core made runs 4-17x slower when one core was busy).

Example::

    parser = sub.add_parser("track"); add_runtime_options(parser)
    return run_command("python -m torchpf", args, _track)
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

#: Environment variable that shows tracebacks instead of one-line errors (same as ``--debug``).
DEBUG_ENV = "TORCHPF_DEBUG"

__all__ = [
    "CliError",
    "add_runtime_options",
    "available_memory",
    "check_memory",
    "check_output_dir",
    "check_output_file",
    "default_threads",
    "int_at_least",
    "run_command",
]


class CliError(ValueError):
    """A user-facing error: printed as one line, exit status 2."""


def default_threads() -> int:
    """Threads for torch: 1 when ``CI`` is set (a shared runner), else the cores free to this process."""
    if os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no"):
        return 1
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity API (macOS, Windows)
        return max(1, os.cpu_count() or 1)


def int_at_least(minimum: int):
    """An argparse ``type``: the argument as an ``int`` >= ``minimum``, else argparse's usage error."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    return parse


_threads = int_at_least(1)


def add_runtime_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--threads N`` and ``--debug`` to a (sub)command parser."""
    parser.add_argument(
        "--threads",
        type=_threads,
        default=None,
        metavar="N",
        help="torch threads (default: the cores free to this process; 1 when the CI variable is set)",
    )
    parser.add_argument(
        "--debug", action="store_true", help=f"show the traceback of an error (or set {DEBUG_ENV}=1)"
    )


def check_output_file(path: str | os.PathLike, option: str = "--out") -> str:
    """``path`` as a string if a file can be written there; a :class:`CliError` before any work otherwise
    (a folder, a file under a non-folder, a folder without write permission)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise CliError(f"{option} {path}: is a directory, expected a file name")
    folder = os.path.dirname(os.path.abspath(path))
    existing = folder
    while not os.path.exists(existing):  # write_atomic creates the missing folders
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise CliError(f"{option} {path}: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise CliError(f"{option} {path}: {existing} is not writable")
    if os.path.exists(path) and not os.access(path, os.W_OK) and not os.access(folder, os.W_OK):
        raise CliError(f"{option} {path}: not writable")
    return path


def check_output_dir(path: str | os.PathLike, option: str = "--out") -> str:
    """``path`` as a string if it is, or can be created as, a writable folder; a :class:`CliError`
    otherwise."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise CliError(f"{option} {path}: exists and is not a directory")
    existing = os.path.abspath(path)
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise CliError(f"{option} {path}: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise CliError(f"{option} {path}: {existing} is not writable")
    return path


def available_memory() -> int | None:
    """Bytes this process can still allocate: ``MemAvailable`` of ``/proc/meminfo``, capped by the cgroup
    limit (containers); None where neither is readable."""
    found = []
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    for limit_file, usage_file in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),
    ):
        try:
            with open(limit_file, encoding="ascii") as f:
                limit = f.read().strip()
            with open(usage_file, encoding="ascii") as f:
                usage = int(f.read().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 1 << 60:
            found.append(max(int(limit) - usage, 0))
        break
    return min(found) if found else None


def check_memory(need: int, what: str) -> None:
    """A :class:`CliError` saying how much ``what`` needs when ``need`` bytes exceed
    :func:`available_memory`: raised before the allocation, not after a swap storm."""
    have = available_memory()
    if have is not None and need > have:
        raise CliError(
            f"{what} needs about {need / 2**30:.1f} GiB of memory, {have / 2**30:.1f} GiB are available"
        )


def _expected_errors() -> tuple[type[BaseException], ...]:
    """Error types that mean bad input or a resource limit, never a bug: reported in one line."""
    known: list[type[BaseException]] = [ValueError, OSError, OverflowError, MemoryError, RecursionError]
    known.append(SystemError)  # OpenCV's Python binding raises it on some malformed files
    cv2 = sys.modules.get("cv2")  # only if a command imported it: never import OpenCV just for this
    if cv2 is not None and isinstance(getattr(cv2, "error", None), type):
        known.append(cv2.error)
    return tuple(known)


def _one_line(error: BaseException) -> str:
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        return f"{error.filename}: {error.strerror}"
    text = " ".join(str(error).split())
    if isinstance(error, MemoryError):
        return f"out of memory{': ' + text if text else ''}"
    if isinstance(error, RecursionError):
        return f"input nested too deeply ({text})"
    if not isinstance(error, ValueError | OSError):  # name the kind where the message alone is cryptic
        text = f"{type(error).__name__}: {text}"
    return text[:1000] or type(error).__name__


def _allocation_failure(error: BaseException) -> bool:
    # torch reports a failed CPU allocation as a RuntimeError ("DefaultCPUAllocator: can't allocate memory:
    # you tried to allocate N bytes") and a CUDA one as torch.OutOfMemoryError (a RuntimeError too).
    text = str(error)
    return isinstance(error, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text)


def run_command(prog: str, args: argparse.Namespace, func: Callable[[argparse.Namespace], int]) -> int:
    """Run ``func(args)`` with the runtime options applied; returns the exit status.

    0 or ``func``'s status on success, 2 with one line on stderr for bad input or a resource limit, 130 on
    Ctrl-C; ``args.debug`` or ``TORCHPF_DEBUG=1`` re-raise instead.
    """
    command = getattr(args, "command", None) or ""
    label = f"{prog} {command}".strip()
    debug = bool(getattr(args, "debug", False)) or os.environ.get(DEBUG_ENV, "") not in ("", "0")
    import torch  # every command computes with it: set its threads before the first operation

    torch.set_num_threads(getattr(args, "threads", None) or default_threads())
    try:
        return func(args)
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{label}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        if debug or not (isinstance(e, _expected_errors()) or _allocation_failure(e)):
            raise
        print(f"{label}: error: {_one_line(e)}", file=sys.stderr)
        return 2
