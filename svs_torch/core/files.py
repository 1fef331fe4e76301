"""Files the package reads and writes: names checked before use, and outputs written whole.

Every writer of the package (figures, label images, captured frames, sweep plots, benchmark reports, CSV tables)
goes through :func:`atomic_output`: the data goes to a temporary file beside the target, which is renamed over it
only when complete, so an interrupted or failed run never leaves half a file; the new file gets the permissions
of any new file, ``0o666`` less the process umask (``tempfile.mkstemp`` would force ``0o600``).

Only the standard library is imported, so that the command line can check file names before torch loads.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shlex
import stat
import sys
import threading
import uuid
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from .errors import InputError

__all__ = ["STDERR_LOCK", "atomic_output", "check_output_file", "check_path_given", "check_writable_folder",
           "display_path", "make_output_folder", "null_device_on", "path_kind", "short_name", "split_list_line",
           "stream_is_terminal", "PROGRESS_HELP", "progress_setting", "redraws_in_place", "tidy_path",
           "write_bytes_atomic", "write_errors_named", "write_failure", "error_text"]

#: Held while descriptor 2 is lent to C decoders to collect what they write (``core.image_files``), and by the
#: command line's own lines on standard error (progress, warnings), so that none of them is written into that
#: window from another thread and lost: eval decodes its next block in a thread, and a log of a 1000-pair eval
#: kept 2 of its 10-odd progress lines (an audit).
STDERR_LOCK = threading.RLock()

#: The longest path shown in an error message; longer ones are cut in the middle.
MAX_SHOWN_CHARS = 120


def display_path(path: str | os.PathLike) -> str:
    """``path`` for a one-line message: at most :data:`MAX_SHOWN_CHARS` characters, control characters escaped."""
    text = str(path)
    if len(text) > MAX_SHOWN_CHARS:
        half = MAX_SHOWN_CHARS // 2 - 1
        text = f"{text[:half]}…{text[-half:]}"
    return text if text.isprintable() else repr(text)[1:-1]


def check_list_file(path: str | os.PathLike, name: str) -> None:
    """Refuse ``path`` unless it is a file, naming ``name`` ("expected a list file, got no file: PATH"; a folder or a
    device likewise). Without torch, so ``estimate --pairs`` says it before the pipeline's imports (2.5 s)."""
    if os.fspath(path) == "-":  # was "got no file: -", which said neither why nor what to give (an audit)
        raise InputError(f"{name}: expected a list file, got '-': standard input is not read as a list (a list is "
                         "read by its name, and again by each worker of estimate); write it to a file (... > "
                         "pairs.txt) and give its name (a file named '-': ./-)")
    kind = path_kind(path, name)
    if kind != "file":
        got = {"folder": "a folder", "missing": "no file"}.get(kind, "a special file")
        if kind == "other" and stat.S_ISFIFO(os.stat(path).st_mode):  # /dev/stdin in a pipeline, <(...): read once
            got = ("a pipe, which gives its lines once (a list is read by its name, and again by each worker of "
                   "estimate): write it to a file and give its name")
        raise InputError(f"{name}: expected a list file, got {got}: {display_path(path)}")


def tidy_path(path: str | os.PathLike) -> str:
    """``path`` without its inner ``..`` ("experiments/../../shared" → "../shared") where that names what the system
    opens; else as it is: through a linked folder ``link/..`` is the folder above the link's target, not the link's
    own, so dropping it by its letters named another file (a sweep refused a path eval ran: an audit)."""
    tidy = os.path.normpath(path)
    return tidy if os.path.realpath(tidy) == os.path.realpath(path) else os.fspath(path)


def path_kind(path: str | os.PathLike, name: str) -> str:
    """What is at ``path``: ``"file"``, ``"folder"``, ``"other"`` (a device, a socket) or ``"missing"``.

    Raises:
        InputError: naming ``name``, for a name no file can have (a NUL character, a name longer than the file
            system allows) or a path that cannot be looked at (no permission on a folder on the way).
    """
    try:
        os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return "missing"
    except (OSError, ValueError) as error:
        reason = getattr(error, "strerror", None) or str(error)
        raise InputError(f"{name}: not a usable path ({reason}): {display_path(path)}") from None
    if os.path.isdir(path):
        return "folder"
    return "file" if os.path.isfile(path) else "other"


def check_path_given(path: str | os.PathLike, name: str, what: str = "a file name") -> None:
    """Refuse an empty (or blank) path, naming ``name`` and ``what`` was expected. Why: ``Path("")`` is the current
    folder, so an empty name (``--out "$OUT"`` with OUT unset) was reported as "the folder '.'" or "a directory".
    Checked before the name becomes a :class:`Path`. A name of another type (None, a number) is refused too: it
    was a TypeError from ``os.fspath`` naming neither the argument nor what it wanted (an audit of the API)."""
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"{name}: expected {what} (str or os.PathLike), got {type(path).__name__}")
    if not os.fspath(path).strip():
        raise InputError(f"{name}: expected {what}, got {os.fspath(path)!r}")


def check_output_file(path: str | os.PathLike, name: str, suffixes: tuple[str, ...] = (),
                      kinds: str = "") -> Path:
    """``path`` as a :class:`Path` if a file can be written there, else :class:`InputError` naming ``name``: the
    folder must exist, the path must not be a folder, and with ``suffixes`` its ending must be one of them
    (``kinds`` says which in the message, e.g. ``"a .png, .pdf or .svg"``). Checked before any work starts."""
    check_path_given(path, name)
    if str(path).endswith(("/", os.sep)):  # Path() drops it: 'x.png/' wrote x.png and was reported as 'x.png/'
        raise InputError(f"{name}: expected a file name, got {display_path(path)!r}, which ends as a folder does")
    target = Path(path)
    kind = path_kind(target, name)
    if kind == "folder":
        raise InputError(f"{name}: expected a file name, got the folder {display_path(target)!r}")
    if kind == "other":  # written whole and renamed over it, a device (/dev/null, /dev/full) became a plain file
        raise InputError(f"{name}: expected a regular file name, got {display_path(target)!r} (a device or other "
                         f"special file)")
    # A link is written through (atomic_output): its target's folder is where the file goes. A dangling link's
    # missing folder failed only once the work was done (an audit).
    written = Path(os.path.realpath(target)) if target.is_symlink() else target
    if written is not target and path_kind(written.parent, name) == "missing":
        raise InputError(f"{name}: {display_path(target)!r} is a link to {display_path(written)!r}, whose folder "
                         f"does not exist")
    _check_parent_folder(written, name)
    if suffixes and target.suffix.lower() not in suffixes:
        raise InputError(f"{name}: expected {kinds or ' or '.join(suffixes)} file name, got {display_path(target)!r}")
    check_writable_folder(written.parent, name)
    return target


def _check_parent_folder(target: Path, name: str) -> None:
    """:class:`InputError` naming ``name`` unless ``target``'s folder exists: one that is a file was said not to
    exist (``--out afile/x.json``: "folder 'afile' does not exist", an audit)."""
    kind = path_kind(target.parent, name)
    if kind == "missing":
        raise InputError(f"{name}: folder {display_path(target.parent)!r} does not exist")
    if kind != "folder":
        raise InputError(f"{name}: {display_path(target.parent)!r} is not a folder (it is "
                         f"{'a file' if kind == 'file' else 'a device or other special file'})")


def check_writable_folder(folder: str | os.PathLike, name: str) -> None:
    """:class:`InputError` naming ``name`` unless a file can be created in the existing ``folder``: tried with an
    empty file, removed at once, since permission bits do not tell (root, a read-only mount, ``/sys``). Checked
    before any work starts, so that one output that cannot be written leaves no other written."""
    probe = Path(folder) / f".svs-depth-write-test.{uuid.uuid4().hex[:8]}"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError as error:
        reason = error.strerror or type(error).__name__
        if error.errno == errno.ENOENT and Path(folder).is_dir():  # /proc: "No such file or directory" (an audit)
            reason = "it takes no new files"
        raise InputError(f"{name}: cannot write in folder {display_path(folder)!r} ({reason})") from None
    with contextlib.suppress(OSError):
        probe.unlink()


def make_output_folder(path: str | os.PathLike, name: str) -> Path:
    """``path`` as a folder to write into, made if missing (one level: its parent must exist); else
    :class:`InputError` naming ``name``. Checked before any work starts."""
    target = Path(path)
    kind = path_kind(target, name) if str(path) else "other"
    if kind == "folder":
        check_writable_folder(target, name)
        return target
    if kind != "missing":
        raise InputError(f"{name}: expected a folder, got {'a file' if kind == 'file' else 'no usable path'}: "
                         f"{display_path(target)!r}")
    _check_parent_folder(target, name)
    try:
        target.mkdir(exist_ok=True)
    except OSError as error:
        raise InputError(f"{name}: cannot make folder {display_path(target)!r} "
                         f"({error.strerror or type(error).__name__})") from None
    return target


def short_name(name: str, limit_bytes: int = 200) -> str:
    """At most ``limit_bytes`` of ``name`` as the file system encodes it, whole characters only: the stem of a
    temporary file beside ``name`` (any name a folder takes, 255 bytes, then leaves room for the temporary's)."""
    return os.fsencode(name)[:limit_bytes].decode(sys.getfilesystemencoding(), "ignore")


@contextlib.contextmanager
def write_errors_named(name: str, path: str | os.PathLike) -> Iterator[None]:
    """An :class:`OSError` in the ``with`` block (a full disk, an I/O error) raised again naming the option
    ``name`` and the file ``path``: the command's failure (exit 1), told as ``--figure: cannot write 'f.png': No
    space left on device`` instead of the bare "No space left on device" that named neither."""
    try:
        yield
    except OSError as error:
        raise write_failure(f"{name}: cannot write {display_path(path)!r}", error) from None


def write_failure(what: str, error: OSError) -> OSError:
    """``error`` of a write said as ``what: <its reason>``: a plain :class:`OSError` keeping its errno, which the
    command line takes as the command's failure (exit 1). Not ``OSError(errno, ...)``: Python makes that a
    PermissionError for EPERM or EACCES (and a FileNotFoundError, ... for others), which it takes as a bad argument
    (exit 2) once the work was done (an audit). A caller that tells an error's kind apart (a FileExistsError) does
    so inside the write, before it is said this way."""
    failure = OSError(f"{what}: {error.strerror or error}")
    failure.errno = error.errno
    return failure


def error_text(error: BaseException) -> str:
    """``error`` as one line for a command's message: an :class:`OSError`'s reason and file without Python's
    ``[Errno 28]`` (capture ended "error: [Errno 28] --out-dir: cannot write ...", the option no longer first, an
    audit), as the command line's own handler says it (``svs_torch.cli.main``); any other error as its text."""
    if isinstance(error, OSError):
        text = f"{error.strerror or error}" + (f": {error.filename}" if error.filename else "")
    else:
        text = str(error)
    return " ".join(text.split())


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, mode: str = "wb", **open_kwargs) -> Iterator[IO]:
    """A stream to write ``path`` whole: a temporary file beside it (same folder, so the rename is atomic),
    renamed over ``path`` when the ``with`` block ends normally and removed when it raises.

    ``mode`` is ``"wb"`` or ``"w"`` (then ``open_kwargs`` such as ``encoding``, ``newline`` go to the text
    stream). The file is created with ``os.open(..., 0o666)``, so the umask (and a folder's default ACL) decides
    its permissions, as for any new file. A symbolic link is written through, its target replaced (renamed over,
    the link itself became a plain file). Where the system has them (Linux), the temporary file has no name
    until it is complete (``O_TMPFILE``): a process killed while writing (SIGKILL, which no handler sees) leaves
    nothing behind; it left a hidden half file (``.sweep.png.1a2b3c4d.tmp``).
    """
    if mode not in ("w", "wb"):
        raise InputError(f"mode: expected 'w' or 'wb', got {mode!r}")
    target = Path(os.path.realpath(path)) if os.path.islink(path) else Path(path)
    temporary = target.with_name(f".{short_name(target.name)}.{uuid.uuid4().hex[:8]}.tmp")
    handle, unnamed = _open_unnamed(target.parent)
    if handle is None:
        # O_BINARY: on Windows a descriptor opens in text mode without it, every \n written as \r\n (a PNG broken)
        handle = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    named = not unnamed
    try:
        with os.fdopen(handle, mode, **open_kwargs) as stream:
            yield stream
            if unnamed:  # named only now, complete (closed unnamed, it would be gone)
                stream.flush()
                _name_unnamed(handle, temporary)
                named = True
        os.replace(temporary, target)
    except BaseException:
        if named:
            with contextlib.suppress(OSError):
                os.unlink(temporary)
        raise


def _name_unnamed(handle: int, name: Path) -> None:
    """Give the unnamed file open as ``handle`` the name ``name`` (``linkat`` following ``/proc/self/fd``'s link:
    ``os.link`` calls it only when given a folder's handle; plain ``link`` would link the link, across devices)."""
    folder = os.open(name.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.link(f"/proc/self/fd/{handle}", name.name, dst_dir_fd=folder, follow_symlinks=True)
    finally:
        os.close(folder)


def _open_unnamed(folder: Path) -> tuple[int | None, bool]:
    """A file without a name in ``folder`` to write (``O_TMPFILE``, named later through ``/proc/self/fd``), or
    ``(None, False)`` where the system or the file system has none."""
    flag = getattr(os, "O_TMPFILE", 0)
    if not flag or not os.path.isdir("/proc/self/fd"):
        return None, False
    try:
        return os.open(folder, os.O_WRONLY | flag, 0o666), True
    except OSError as error:
        if error.errno in (errno.EISDIR, errno.EOPNOTSUPP, errno.EINVAL, errno.ENOENT, errno.ENOTSUP):
            return None, False  # an older kernel, a file system without it: a named temporary file
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` whole (see :func:`atomic_output`)."""
    with atomic_output(path) as stream:
        stream.write(data)


def split_list_line(line: str) -> list[str]:
    """A list file's line as its fields, split as a POSIX shell splits words: quotes and backslashes group, and
    ``#`` starts a comment only at the start of a word (``take#2/left.png`` is a path; ``shlex.split`` with
    ``comments=True`` cut it at the ``#``). Raises ValueError for unbalanced quotes, as ``shlex.split`` does. On
    Windows a backslash is the path separator, not an escape (``C:\\data\\left.png``; it was ``C:dataleft.png``, no
    such file): only quotes group there, as in its own shells."""
    literal = sys.platform == "win32"
    quote, word_starts, index = None, True, 0
    while index < len(line):
        char = line[index]
        if quote is not None:
            if char == quote:
                quote = None
            elif char == "\\" and quote == '"' and not literal:
                index += 1  # an escaped character inside double quotes
        elif char == "\\" and not literal:
            index += 1  # an escaped character: never a comment or a quote
        elif char in "'\"":
            quote = char
        elif char == "#" and word_starts:
            line = line[:index]
            break
        word_starts = quote is None and char.isspace()
        index += 1
    lexer = shlex.shlex(line, posix=True)
    lexer.whitespace_split, lexer.commenters = True, ""
    if literal:
        lexer.escape = ""
    return list(lexer)


def null_device_on(fd: int) -> None:
    """Descriptor ``fd`` (open or closed) made the null device, read-only for 0, write-only otherwise: what a
    closed standard stream becomes (``svs_torch.cli.main``), and guide's ``--json`` stream once its disk is full
    (``svs_torch.cli.guide_log``). Held on ``fd`` itself, so that no file opened later is given it."""
    null = os.open(os.devnull, os.O_RDONLY if fd == 0 else os.O_WRONLY)
    if null != fd:
        try:
            os.dup2(null, fd)
        finally:
            os.close(null)


def stream_is_terminal(stream: IO | None) -> bool:
    """Whether ``stream`` is a terminal (redrawn lines, bars) rather than a file, a pipe or nothing (plain lines)."""
    try:
        return stream is not None and stream.isatty()
    except (AttributeError, ValueError):  # a stream without a terminal behind it, or closed
        return False


#: What ``svs-depth --help`` says of :func:`progress_setting`.
PROGRESS_HELP = """\
Progress bars and guide's status line: SVS_TORCH_PROGRESS=plain makes them a plain line every 5 s on a terminal
too (for a screen reader or a braille display), SVS_TORCH_PROGRESS=off silences them (results, warnings and spoken
messages still print); into a file or a pipe, or on a TERM=dumb terminal, they are plain lines."""


def progress_setting() -> str:
    """``SVS_TORCH_PROGRESS``: ``"plain"`` (a plain line every few seconds even on a terminal: a screen reader or a
    braille display follows lines, not a bar redrawn several times a second), ``"off"`` (no progress nor status
    lines at all; results, warnings and messages still print) or ``"auto"`` (unset, empty or ``auto``); any other
    value is warned of once a process and taken as ``"auto"`` (a mistyped ``quiet`` went unsaid)."""
    setting = os.environ.get("SVS_TORCH_PROGRESS", "").strip().lower()
    if setting not in ("plain", "off", "auto", ""):
        if setting not in _PROGRESS_WARNED:
            _PROGRESS_WARNED.add(setting)
            warnings.warn(f"SVS_TORCH_PROGRESS={setting!r}: expected plain or off (or auto, the default); "
                          f"progress is shown as without it", stacklevel=2)
        return "auto"
    return setting or "auto"


#: The unknown ``SVS_TORCH_PROGRESS`` values warned of already (once each a process).
_PROGRESS_WARNED: set[str] = set()


def redraws_in_place(stream: IO | None) -> bool:
    """Whether progress on ``stream`` may be a bar or a status line redrawn in place (``\\r``): a terminal, but not
    one that says ``TERM=dumb`` (an Emacs shell buffer, emacspeak's, an editor's or a runner's pseudo-terminal),
    which shows each redraw as more text on one line and reads every one aloud, nor when
    :func:`progress_setting` is not ``"auto"``; there, as into a file or a pipe, progress is a plain line every
    few seconds (or none)."""
    return (stream_is_terminal(stream) and os.environ.get("TERM", "").strip().lower() != "dumb"
            and progress_setting() == "auto")
