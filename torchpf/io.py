"""File helpers shared by the packages: atomic writes and the mocap CSV format.

Mocap CSV (``DESIGN.md``): a header row, an optional first column ``time`` (s), then one column per DOF
named as in ``Skeleton.dof_names`` (radians / metres), one row per frame::

    time,Hips_Xposition,Hips_Yposition,...,LeftUpLeg_Zrotation,...
    0.0,0.50077,-1.78968,...,0.1312,...
    0.008333,0.50105,-1.78970,...,0.1309,...

The functions here are the low-level format (numpy arrays in, numpy arrays out), shared by ``training``
(``training.mocap.save_csv``/``load_csv`` build a ``Motion`` on top, with the frame rate) and by torchpf's
own writers (a synthetic sequence's ``truth.csv``). Values are written with Python's ``repr`` (the shortest
text that reads back to the same float64), so a write/read round trip is bit-exact.

Every malformed input raises :class:`MocapFormatError` (a ``ValueError``) whose message names the file, the
line and, where it applies, the column, e.g. ``walk.csv:12: column 3 ('Hips_Zposition'): not a number: 'x'``.

Example::

    write_mocap_csv("truth.csv", skel.dof_names, theta, times=t)      # theta (T, D), t (T,)
    names, times, theta = read_mocap_csv("truth.csv", expected_dof_names=skel.dof_names)
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from collections.abc import Sequence

import numpy as np

#: Name of the optional first column (seconds).
TIME_COLUMN = "time"
# Characters a column name may not contain: the writer does no quoting, so that any CSV reader (and a
# person with a text editor) sees exactly one name per comma-separated field.
_FORBIDDEN_IN_NAMES = (",", '"', "\n", "\r")


# A number as the file formats write it: ASCII digits, optional sign, point and exponent (or inf / nan, which
# the callers refuse with their own "must be finite"). Python's float() also takes "1_000", Arabic-Indic
# digits and Unicode spaces: a file holding those was not written by a number formatter.
_PLAIN_NUMBER = re.compile(
    r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)", re.IGNORECASE
)


def plain_float(text: str) -> float:
    """``float(text)`` for a plain ASCII decimal number (surrounding ASCII blanks allowed).

    Raises ValueError for anything else that :func:`float` would accept: digit group underscores
    (``1_000``), non-ASCII digits (Arabic-Indic ``١٢``), Unicode spaces. ``inf``/``nan`` pass (callers check
    finiteness with their own message).
    """
    stripped = text.strip(" \t\r\n")
    if not _PLAIN_NUMBER.fullmatch(stripped):
        raise ValueError(f"not a plain decimal number: {text!r}")
    return float(stripped)


def load_yaml(text: str):
    """``yaml.safe_load(text)`` where only plain ASCII decimal numbers are numbers: YAML 1.1's ``1_000``
    (digit groups), ``0x1f``, ``0o17`` and ``1:30`` (sexagesimal) stay strings, so a loader's type check
    refuses them with its own message naming the key, instead of silently reading 1000, 31, 15 or 90 (a
    camera named ``0_1`` would become the integer 1). Exponents without a dot (``1e-3``) are floats."""
    import yaml

    int_tag, float_tag = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"

    class Loader(yaml.SafeLoader):
        pass

    Loader.yaml_implicit_resolvers = {
        first: [(tag, rx) for tag, rx in resolvers if tag not in (int_tag, float_tag)]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }
    Loader.add_implicit_resolver(int_tag, re.compile(r"^[-+]?[0-9]+$"), list("-+0123456789"))
    Loader.add_implicit_resolver(
        float_tag,
        re.compile(
            r"^[-+]?(?:[0-9]+\.[0-9]*|\.[0-9]+|[0-9]+)(?:[eE][-+]?[0-9]+)?$|^[-+]?\.(?:inf|Inf|INF)$|^\.(?:nan|NaN|NAN)$"
        ),
        list("-+0123456789."),
    )
    return yaml.load(text, Loader=Loader)  # noqa: S506 (a SafeLoader with narrower number resolvers)


def plain_int(text: str) -> int:
    """``int(text)`` for plain ASCII digits with an optional sign (no ``1_000``, no non-ASCII digits)."""
    stripped = text.strip(" \t\r\n")
    if not re.fullmatch(r"[+-]?[0-9]+", stripped):
        raise ValueError(f"not a plain integer: {text!r}")
    return int(stripped)


class MocapFormatError(ValueError):
    """Malformed mocap file (CSV or BVH). ``path``, ``line`` (1-based) and ``column`` say where."""

    def __init__(
        self,
        message: str,
        *,
        path: str | os.PathLike | None = None,
        line: int | None = None,
        column: str | None = None,
    ):
        self.path = None if path is None else os.fspath(path)
        self.line = line
        self.column = column
        self.reason = message
        where = self.path if self.path is not None else "<mocap>"
        if line is not None:
            where += f":{line}"
        text = f"{where}: "
        if column is not None:
            text += f"column {column}: "
        super().__init__(text + message)

    def __reduce__(self):  # keep keyword-only fields through pickling (multiprocessing, pytest-xdist)
        return (_rebuild_error, (self.reason, self.path, self.line, self.column))


def _rebuild_error(message, path, line, column):
    return MocapFormatError(message, path=path, line=line, column=column)


# Hidden temporaries are named ``.tmp-<pid>-<random>-<target name>``: the pid says whether the writer is
# still alive, so a later write can remove what a killed one (SIGKILL, power loss) left behind.
_TMP_PREFIX = ".tmp-"
_STALE_AGE_S = 24 * 3600.0  # pids are reused: past this age a temporary is stale whatever its pid says
_LEGACY_STALE_AGE_S = 3600.0  # temporaries of older versions carry no pid
_CLEAN_INTERVAL_S = 60.0  # a folder is scanned at most this often (write_sequence writes thousands of files)
_last_clean: dict[str, float] = {}


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True  # another thread of this process may be writing it
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists (another user's) or cannot tell: keep the file
    return True


def clean_stale_temporaries(folder: str | os.PathLike) -> list[str]:
    """Remove the hidden ``.tmp-*`` files that an interrupted :func:`write_atomic` left in ``folder``.

    A temporary is stale when the process that wrote it is gone, or when it is older than a day (older
    than an hour for temporaries without a pid in the name). Called by :func:`write_atomic` (at most once a
    minute per folder); returns the removed paths.
    """
    import re
    import time

    folder = os.fspath(folder)
    now = time.time()
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        if not entry.name.startswith(_TMP_PREFIX):
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            age = now - entry.stat(follow_symlinks=False).st_mtime
        except OSError:
            continue
        m = re.match(r"\.tmp-(\d+)-", entry.name)
        if m is not None:
            stale = age > _STALE_AGE_S or not _pid_alive(int(m.group(1)))
        else:
            stale = age > _LEGACY_STALE_AGE_S
        if stale:
            try:
                os.unlink(entry.path)
                removed.append(entry.path)
            except OSError:
                pass
    return removed


def _maybe_clean(folder: str) -> None:
    import time

    now = time.monotonic()
    if now - _last_clean.get(folder, -math.inf) >= _CLEAN_INTERVAL_S:
        _last_clean[folder] = now
        clean_stale_temporaries(folder)


def file_mode(path: str | os.PathLike) -> int:
    """The permission bits ``open(path, "w")`` leaves: an existing file's own, else ``0o666`` less the
    umask (``0o644`` with the usual umask 022). :func:`write_atomic` gives its temporary file these, since
    ``tempfile.mkstemp`` creates ``0o600`` files that other users could not read once renamed."""
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        pass
    try:  # Linux: read the umask without changing it (os.umask would, for every thread, for a moment)
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def write_atomic(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (bytes, or text as UTF-8 with LF line ends) to ``path`` atomically.

    The data goes to a hidden temporary file in the same folder, then ``os.replace`` puts it in place: a
    crash mid-write leaves the previous file intact. Parent folders are created; the file gets the
    permissions a plain write would give it (:func:`file_mode`). Temporaries left by a killed writer are
    removed here (:func:`clean_stale_temporaries`).
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    _maybe_clean(folder)
    mode = file_mode(path)
    fd, tmp = tempfile.mkstemp(
        dir=folder, prefix=f"{_TMP_PREFIX}{os.getpid()}-", suffix=os.path.basename(path)
    )
    try:
        if hasattr(os, "fchmod"):  # POSIX; on Windows mkstemp's file is writable and readable anyway
            os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode("utf-8") if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (see :func:`write_atomic`)."""
    write_atomic(path, text)


# ----------------------------------------------------------------------------------------------- mocap CSV
def _as_float64(values) -> np.ndarray:
    # Tensors are accepted without importing torch here: anything with .detach() is moved to host memory.
    if hasattr(values, "detach"):
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=np.float64)


def _check_names(dof_names: Sequence[str], path) -> list[str]:
    names = list(dof_names)
    for i, n in enumerate(names):
        if not isinstance(n, str) or not n or n != n.strip() or any(c in n for c in _FORBIDDEN_IN_NAMES):
            raise ValueError(
                f"{path}: DOF name {i} is {n!r}: names must be non-empty strings without surrounding "
                f"whitespace, commas, quotes or line breaks"
            )
        if n == TIME_COLUMN:
            raise ValueError(f"{path}: a DOF may not be named {TIME_COLUMN!r} (reserved for the time column)")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{path}: duplicate DOF names {dup}")
    return names


def _check_values(arr: np.ndarray, names: list[str], path: str, first_row: int = 0) -> None:
    if arr.ndim != 2 or arr.shape[1] != len(names):
        raise ValueError(f"{path}: values must have shape (T, {len(names)}), got {arr.shape}")
    bad = np.argwhere(~np.isfinite(arr))
    if len(bad):
        t, d = bad[0]
        raise ValueError(
            f"{path}: values[{t + first_row}, {d}] ({names[d]!r}) is {arr[t, d]}; must be finite"
        )


def _csv_lines(arr: np.ndarray) -> str:
    # float.__repr__ is the shortest string that round-trips; tolist() gives Python floats (numpy scalars'
    # repr would read "np.float64(...)").
    return "".join(",".join(map(repr, row)) + "\n" for row in arr.tolist())


def write_mocap_csv(
    path: str | os.PathLike,
    dof_names: Sequence[str],
    values,
    times=None,
) -> None:
    """Write a mocap CSV atomically (a crash leaves any previous file intact).

    Args:
        path: file to write; parent folders are created.
        dof_names: (D,) column names, e.g. ``Skeleton.dof_names``. Non-empty, unique, no ``,``/``"``/line
            breaks/surrounding whitespace, not ``"time"``.
        values: (T, D) finite values (rad / m); numpy array, torch tensor or nested lists.
        times: optional (T,) finite, strictly increasing times (s), written as the first column ``time``.

    Every value is written with full float64 precision (``repr``), so :func:`read_mocap_csv` gives back the
    same bits. :class:`MocapCsvWriter` writes the same format row by row.
    """
    names = _check_names(dof_names, os.fspath(path))
    arr = _as_float64(values)
    _check_values(arr, names, os.fspath(path))
    header = names
    if times is not None:
        t_arr = _as_float64(times)
        if t_arr.shape != (arr.shape[0],):
            raise ValueError(f"{os.fspath(path)}: times must have shape ({arr.shape[0]},), got {t_arr.shape}")
        if not np.isfinite(t_arr).all() or np.any(np.diff(t_arr) <= 0):
            raise ValueError(f"{os.fspath(path)}: times must be finite and strictly increasing")
        arr = np.concatenate([t_arr[:, None], arr], axis=1)
        header = [TIME_COLUMN, *names]
    write_text_atomic(path, ",".join(header) + "\n" + _csv_lines(arr))


class MocapCsvWriter:
    """Write a mocap CSV (the format of :func:`write_mocap_csv`) row by row, as results come.

    Rows go to ``<path>.partial`` and are flushed as they are written, so a crash (or Ctrl-C) keeps every
    finished row in a readable mocap CSV; :meth:`close` then moves the file to ``path`` in one
    ``os.replace`` (atomic: ``path`` is either the previous file or the complete new one).

    Args:
        path: the final file; parent folders are created.
        dof_names: (D,) column names (rules of :func:`write_mocap_csv`).
        fps: when given, a ``time`` column ``t / fps`` (s) comes first.

    Example::

        with MocapCsvWriter("track.csv", skel.dof_names, fps=30) as out:
            for theta in estimates:          # (D,) or (n, D) per call
                out.write(theta)
        # an exception inside the block leaves track.csv.partial with the rows written so far
    """

    def __init__(self, path: str | os.PathLike, dof_names: Sequence[str], fps: float | None = None):
        self.path = os.fspath(path)
        self.names = _check_names(dof_names, self.path)
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"{self.path}: fps must be positive and finite, got {fps}")
        self.fps = fps
        self.partial = self.path + ".partial"
        self.rows = 0
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        self._file = open(self.partial, "w", encoding="utf-8", newline="\n")  # noqa: SIM115 (closed in close)
        header = ([TIME_COLUMN] if fps is not None else []) + self.names
        self._file.write(",".join(header) + "\n")
        self._file.flush()

    def write(self, values) -> None:
        """Append rows: ``values`` (D,) or (n, D) finite (rad / m)."""
        arr = _as_float64(values)
        arr = arr[None] if arr.ndim == 1 else arr
        _check_values(arr, self.names, self.partial, first_row=self.rows)
        if self.fps is not None:
            t = (self.rows + np.arange(arr.shape[0], dtype=np.float64)) / self.fps
            arr = np.concatenate([t[:, None], arr], axis=1)
        self._file.write(_csv_lines(arr))
        self._file.flush()
        self.rows += arr.shape[0]

    def close(self) -> None:
        """Finish: ``<path>.partial`` becomes ``path`` (atomically)."""
        if self._file.closed:
            return
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        os.replace(self.partial, self.path)

    def abort(self) -> None:
        """Stop without finishing: the rows written so far stay in ``<path>.partial``."""
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> MocapCsvWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _column_label(index: int, name: str) -> str:
    return f"{index + 1} ({name!r})"


def read_mocap_csv(
    path: str | os.PathLike,
    expected_dof_names: Sequence[str] | None = None,
) -> tuple[list[str], np.ndarray | None, np.ndarray]:
    """Read a mocap CSV.

    Args:
        path: the file (UTF-8; LF or CRLF line ends; trailing blank lines are ignored).
        expected_dof_names: if given, the file must have exactly these DOF columns (in any order) and the
            result is returned in this order; otherwise columns come back in file order.

    Returns:
        ``(dof_names, times, values)``: ``dof_names`` (D,) list of str; ``times`` (T,) float64 seconds, or
        ``None`` when the file has no ``time`` column; ``values`` (T, D) float64.

    Raises:
        MocapFormatError: empty file, empty/duplicate/misplaced column names, columns that differ from
            ``expected_dof_names`` (unknown or missing), a row with the wrong number of fields, a field that
            is not a plain decimal number (:func:`plain_float`) or is NaN/inf, times not strictly
            increasing. The message names file, line and
            column.
        FileNotFoundError: no such file.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:  # -sig: tolerate a BOM from spreadsheets
            text = f.read()
    except UnicodeDecodeError as e:
        raise MocapFormatError(f"not UTF-8 text ({e.reason} at byte {e.start})", path=path) from None
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise MocapFormatError("empty file (expected a header row of column names)", path=path, line=1)

    header = [h.strip() for h in lines[0].split(",")]
    for i, h in enumerate(header):
        if not h:
            raise MocapFormatError("empty column name", path=path, line=1, column=str(i + 1))
        if h == TIME_COLUMN and i > 0:
            raise MocapFormatError(
                f"{TIME_COLUMN!r} must be the first column", path=path, line=1, column=_column_label(i, h)
            )
    seen: dict[str, int] = {}
    for i, h in enumerate(header):
        if h in seen:
            raise MocapFormatError(
                f"duplicate column name (also column {seen[h] + 1})",
                path=path,
                line=1,
                column=_column_label(i, h),
            )
        seen[h] = i
    has_time = header[0] == TIME_COLUMN
    first = 1 if has_time else 0
    names = header[first:]

    order = None
    if expected_dof_names is not None:
        expected = list(expected_dof_names)
        if len(set(expected)) != len(expected):
            raise ValueError(
                f"expected_dof_names has duplicates: {sorted({n for n in expected if expected.count(n) > 1})}"
            )
        exp_set, name_set = set(expected), set(names)
        unknown = [n for n in names if n not in exp_set]
        missing = [n for n in expected if n not in name_set]
        if unknown or missing:
            parts = []
            if unknown:
                parts.append(f"unknown column(s) {unknown}")
            if missing:
                parts.append(f"missing column(s) {missing}")
            col = _column_label(header.index(unknown[0]), unknown[0]) if unknown else None
            raise MocapFormatError(
                "columns do not match the expected DOF names: " + "; ".join(parts),
                path=path,
                line=1,
                column=col,
            )
        order = [first + names.index(n) for n in expected]
        names = expected

    n_cols = len(header)
    rows = lines[1:]
    tokens: list[str] = []
    for k, line in enumerate(rows):
        n = line.count(",") + 1
        if n != n_cols or not line.strip():
            what = "empty line" if not line.strip() else f"{n} fields"
            raise MocapFormatError(f"expected {n_cols} fields, got {what}", path=path, line=k + 2)
        tokens.extend(line.split(","))
    data = parse_float_table(tokens, n_cols, header, path, lines=2)

    bad = np.argwhere(~np.isfinite(data))
    if len(bad):
        r, c = bad[0]
        raise MocapFormatError(
            f"value must be finite, got {tokens[r * n_cols + c].strip()!r}",
            path=path,
            line=int(r) + 2,
            column=_column_label(int(c), header[c]),
        )
    times = None
    if has_time:
        times = data[:, 0].copy()
        steps = np.diff(times)
        if np.any(steps <= 0):
            r = int(np.argmax(steps <= 0)) + 1
            raise MocapFormatError(
                f"times must be strictly increasing ({float(times[r - 1])!r} then {float(times[r])!r})",
                path=path,
                line=r + 2,
                column=_column_label(0, TIME_COLUMN),
            )
    values = data[:, order] if order is not None else data[:, first:]
    return names, times, np.ascontiguousarray(values)


def parse_float_table(
    tokens: list[str], n_cols: int, header: Sequence[str], path: str, lines: int | Sequence[int]
) -> np.ndarray:
    """(R, n_cols) float64 from row-major string fields; names the first bad field on failure.

    ``lines`` is the file line of the first row (rows on consecutive lines) or the line of every row; the
    :class:`MocapFormatError` for a field that is not a number names that line and the column.
    """

    def first_bad() -> MocapFormatError | None:
        for i, tok in enumerate(tokens):
            try:
                plain_float(tok)
            except ValueError:
                try:
                    float(tok)
                    what = "not a plain decimal number"  # "1_000", Arabic-Indic digits: float() takes them
                except ValueError:
                    what = "not a number"
                r, c = divmod(i, n_cols)
                return MocapFormatError(
                    f"{what}: {tok.strip()!r}",
                    path=path,
                    line=r + lines if isinstance(lines, int) else lines[r],
                    column=_column_label(c, header[c]),
                )
        return None

    joined = "".join(tokens)
    if "_" in joined or not joined.isascii():  # cheap screen before the per-field check
        error = first_bad()
        if error is not None:
            raise error
    try:
        flat = np.array(tokens, dtype=np.float64)
    except ValueError:
        error = first_bad()  # slow path only to locate the culprit for the message
        if error is not None:
            raise error from None
        raise  # numpy rejected something plain_float accepts: let its message through
    return flat.reshape(-1, n_cols)


# Deflate expands at most ~1032:1; a member claiming more than this ratio has a forged size field.
_MAX_DEFLATE_RATIO = 1100


def _npz_member(zf, info, path: str) -> np.ndarray:
    """One ``.npy`` member of an open zip, its declared size checked against the bytes the zip holds
    before anything is allocated (a mutated header can claim a shape of hundreds of GiB)."""
    import zipfile

    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise ValueError(
            f"member {info.filename!r}: compression method {info.compress_type} is not supported"
        )
    limit = (
        info.compress_size
        if info.compress_type == zipfile.ZIP_STORED
        else (info.compress_size * _MAX_DEFLATE_RATIO + 1024)
    )
    if info.file_size > limit:
        raise ValueError(f"member {info.filename!r}: size field {info.file_size} is corrupt")
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"member {info.filename!r}: .npy format version {version} is not supported")
        if dtype.hasobject:
            raise ValueError(f"member {info.filename!r}: object arrays are not read (no unpickling)")
        nbytes = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
        if nbytes > info.file_size:
            raise ValueError(
                f"member {info.filename!r} declares shape {shape} of {dtype} ({nbytes} bytes) but holds "
                f"{info.file_size} bytes"
            )
    with zf.open(info) as f:
        return np.lib.format.read_array(f, allow_pickle=False)


def read_npz(
    path: str | os.PathLike, what: str, error: type[Exception] = ValueError
) -> dict[str, np.ndarray]:
    """The arrays of a ``.npz`` file, read defensively (untrusted input).

    Every failure raises ``error`` with a message that starts with the path (not a zip, a corrupt or
    unsupported member, an object array, a member whose declared shape needs more bytes than the file
    holds: checked before allocating, so memory stays bounded by the file's own size); a missing file
    raises ``FileNotFoundError`` naming it. Nothing is unpickled. ``what`` names the kind of file
    (``"keypoints"``).
    """
    import tokenize
    import zipfile
    import zlib

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{what.replace('-', ' ')} file not found: {path}")
    try:
        with zipfile.ZipFile(path) as zf:
            return {
                info.filename[: -len(".npy")]: _npz_member(zf, info, path)
                for info in zf.infolist()
                if info.filename.endswith(".npy")
            }
    except (
        zipfile.BadZipFile,
        zlib.error,
        ValueError,
        EOFError,
        OSError,
        KeyError,
        NotImplementedError,
        tokenize.TokenError,
        SyntaxError,
        MemoryError,
        RecursionError,
        OverflowError,
        TypeError,
    ) as e:
        reason = " ".join(str(e).split())[:200]
        raise error(f"{path}: not a readable {what} .npz file ({type(e).__name__}: {reason})") from None


def read_versioned_npz(
    path: str | os.PathLike,
    fmt: str,
    max_version: int,
    what: str,
    error: type[Exception] = ValueError,
) -> tuple[dict[str, np.ndarray], dict, int]:
    """Read a library ``.npz`` file: its arrays, its JSON ``metadata`` entry and format version.

    ``fmt`` is the format name the metadata must carry (``"metadata": {"format": fmt, "version": v, ...}``),
    ``max_version`` the newest version this code reads, ``what`` the kind of file for messages (``"action
    model"``). Every failure raises ``error`` with a message that starts with the path: not a readable zip
    (:func:`read_npz`), no or invalid metadata, another format, a version that is not a positive int or
    newer than ``max_version``; a missing file raises ``FileNotFoundError`` naming it. Nothing is
    unpickled.
    """
    import json

    path = os.fspath(path)

    def bad(reason: str) -> Exception:
        return error(f"{path}: {reason}")

    data = read_npz(path, what, error)
    article = "an" if what[:1].lower() in "aeiou" else "a"
    if "metadata" not in data:
        raise bad(f"not {article} {what} file (no 'metadata' entry)")
    try:
        meta = json.loads(str(data["metadata"]))
    except (ValueError, TypeError, RecursionError) as e:
        raise bad(f"metadata is not valid JSON ({e})") from None
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        raise bad(f"not {article} {what} file (metadata format is not {fmt!r})")
    version = meta.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise bad(f"bad format version {version!r}")
    if version > max_version:
        raise bad(f"format version {version} is newer than this torchpf reads ({max_version}); upgrade")
    return data, meta, version
