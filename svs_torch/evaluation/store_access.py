"""Who may write a results store (:mod:`.store`), and its refusals in words of the store: the claims of sweeps
running at once, a store that is read-only, a schema this code does not read.

Claims: a sweep holds each of its configurations in the store while it runs, as a lock on one byte of the
file far past SQLite's own lock bytes (an open-file-description lock, ``F_OFD_SETLK``: closing another handle
of the file does not drop it, and the system drops it when the process ends, even killed). Two sweeps of
different configurations (two grids, a job array) run together on one store; a sweep any of whose
configurations another running sweep holds is refused before it runs anything (its tasks would have run
twice). Where the system has no such locks (not Linux), a sweep holds the whole store (``flock`` on a
``.sweep-lock`` file beside it).
The claims' handle is closed after the store's connection where the claims are taken (closing any handle of a
file drops the process's own POSIX locks on it, SQLite's among them), and at once where they are refused (the
store is then only closed).

Writes wait for another connection's write (:func:`while_locked`) in short slices of SQLite's own wait with Python's
in between, where Ctrl-C and SIGTERM land at once.
"""

from __future__ import annotations

import errno
import hashlib
import os
import sqlite3
import struct
import time
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, TypeVar

from ..core.errors import InputError
from ..core.files import check_path_given, check_writable_folder, path_kind

__all__ = ["BUSY_TIMEOUT_S", "SQLITE_CANTOPEN", "SQLITE_READONLY", "STORE_TABLES", "WRITERS", "check_schema_version",
           "check_store_path", "claim_configs", "foreign_tables", "raise_if_disk_failed", "read_only_error",
           "sweep_is_writing", "unreadable_beside_writer", "while_locked"]

#: SQLite's primary result codes for a write to a file it opened read-only, and a file it cannot open (sqlite3.h).
SQLITE_READONLY, SQLITE_CANTOPEN = 8, 14
#: SQLite's primary result codes for a failed write (sqlite3.h): SQLITE_IOERR, SQLITE_FULL; and for a store another
#: connection kept locked past the wait: SQLITE_BUSY, SQLITE_LOCKED.
SQLITE_IOERR, SQLITE_FULL, SQLITE_BUSY, SQLITE_LOCKED = 10, 13, 5, 6
#: Seconds a connection waits for another's write to end before it gives up (SQLITE_BUSY).
BUSY_TIMEOUT_S = 60.0
#: Seconds of each of SQLite's own waits for a write lock (:func:`while_locked`). SQLite waits in C, where Python's
#: signal handlers wait for it to return: eval --db and sweep stopped only when another program let go of the lock
#: they waited for, 15-38 s after a Ctrl-C (an audit).
BUSY_SLICE_S = 0.05
#: Seconds of waiting for a write lock after which the wait is said (a warning): a run held by it looked hung.
BUSY_NOTICE_S = 2.0

_Result = TypeVar("_Result")

#: The first byte of the claims, far past SQLite's lock bytes (at 1 GiB) and any store's size; claims never read
#: or write the file.
_CLAIMS_START = 1 << 40
#: The byte held while a sweep takes its claims, so that two sweeps starting at once do not each take a part.
_CLAIMING_BYTE = _CLAIMS_START - 1
#: ``struct flock`` on 64-bit Linux: l_type, l_whence (short), l_start, l_len (off_t), l_pid (pid_t), padding.
_FLOCK = "hhqqi4x"


def _byte_of(config_id: str) -> int:
    return _CLAIMS_START + 1 + int.from_bytes(hashlib.sha256(config_id.encode()).digest()[:5], "big")


def _lock(fcntl, handle: IO, command: int, offset: int, kind: int) -> bool:
    """An open-file-description lock of one byte (:data:`_FLOCK`, the pid 0); False where another handle holds
    it. A file system that takes no locks (``ENOLCK``, ``EINVAL``: some network or FUSE mounts) holds nothing and
    refuses nothing: it was "another sweep is writing" with none."""
    request = struct.pack(_FLOCK, kind, 0, offset, 1, 0)
    try:
        fcntl.fcntl(handle.fileno(), command, request)
    except OSError as error:
        return error.errno not in (errno.EAGAIN, errno.EACCES)
    return True


def claim_configs(path: Path, config_ids: Iterable[str]) -> IO | None:
    """Hold ``config_ids`` in the store ``path`` for this process (module docstring) until the returned handle is
    closed (None where the system has no locks at all).

    Raises:
        InputError: naming ``db``, where another process holds any of them (the store, without OFD locks)."""
    try:
        import fcntl
    except ImportError:  # (Windows: nothing held)
        return None
    wanted = sorted(set(config_ids))
    ofd = getattr(fcntl, "F_OFD_SETLK", None) if struct.calcsize("q") == 8 else None
    if ofd is None:
        # On a file beside the store: on the BSDs (macOS) flock and the record locks SQLite holds on the store itself
        # are one list, and this connection's own shared lock made every sweep "another sweep is writing".
        try:
            handle = open(f"{os.path.realpath(path)}.sweep-lock", "ab")  # noqa: SIM115 (held until the store closes)
        except OSError:  # a folder that takes no new file: nothing held (as where no locks are taken)
            return None
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            return handle
        except OSError as error:
            handle.close()
            if error.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):  # no locks there (see _lock)
                return None
            raise InputError(f"db: another run ({WRITERS}) is writing {path}; run this one once it has "
                             "ended (it then runs only what is missing), or give another store") from None
    # Opened to write (a write lock needs it), never written.
    handle = open(path, "r+b")  # noqa: SIM115 (held open until the store closes)
    _lock(fcntl, handle, fcntl.F_OFD_SETLKW, _CLAIMING_BYTE, fcntl.F_WRLCK)  # waits for another's claiming only
    held = [config_id for config_id in wanted if not _lock(fcntl, handle, ofd, _byte_of(config_id), fcntl.F_WRLCK)]
    _lock(fcntl, handle, ofd, _CLAIMING_BYTE, fcntl.F_UNLCK)
    if held:
        handle.close()
        raise InputError(f"db: another run ({WRITERS}) is writing {path} and running {len(held)} of "
                         f"this run's {len(wanted)} configuration{'s' * (len(wanted) != 1)}; run this one once it has "
                         "ended (it then runs only what is missing), or give another store")
    return handle


#: Who holds configurations in a store while it runs (:func:`claim_configs`), as the refusals and ``results`` say.
WRITERS = "a sweep or an eval --db"


def sweep_is_writing(path: str | Path) -> bool:
    """Whether :data:`WRITERS` hold configurations in the store ``path`` now (False where that cannot be
    told: no OFD locks, a file that cannot be opened). Call it before the store is opened in this process: closing a
    handle of the file drops the process's own SQLite locks on it."""
    try:
        import fcntl

        command = fcntl.F_OFD_GETLK
    except (ImportError, AttributeError):
        return False
    if struct.calcsize("q") != 8 or not os.path.isfile(path):  # (a FIFO's open would wait for a writer)
        return False
    try:
        with open(path, "rb") as handle:
            answer = fcntl.fcntl(handle.fileno(), command, struct.pack(_FLOCK, fcntl.F_RDLCK, 0, _CLAIMS_START,
                                                                       1 << 41, 0))
    except OSError:
        return False
    return struct.unpack(_FLOCK, answer)[0] != fcntl.F_UNLCK


def read_only_error(path: Path) -> InputError:
    """The refusal of a store SQLite could not write as it is read-only (its permissions, an immutable file); it
    was "not a results store (attempt to write a readonly database)"."""
    return InputError(f"db: cannot write {path}: the file is read-only (svs-depth results reads it); make it "
                      "writable, or copy it to a new file and name that")


def unreadable_beside_writer(path: Path) -> str:
    """Why a store with rows still in its ``-wal`` file cannot be read from a folder this user cannot write
    (SQLite reads them through a shared-memory file it makes beside the store): it was "not a results store
    (unable to open database file)" (an audit: a colleague's sweep writing a store on a share)."""
    return (f"db: cannot read {path} from here yet: rows are still in {path.name}-wal (a sweep writing it, or one "
            "killed), and reading them needs a file made in its folder, which this user cannot write; read it once "
            "the writer has ended, or copy both files to a folder you can write")


#: The tables of a results store (:mod:`.store`), beside SQLite's own (``sqlite_*``: the runs' AUTOINCREMENT
#: counter, an ANALYZE's statistics).
STORE_TABLES = frozenset({"meta", "configs", "pairs", "runs", "results"})


def foreign_tables(connection: sqlite3.Connection) -> str | None:
    """What makes an SQLite file another program's, in words, or None for a results store, whole or being made by
    another sweep at this moment (its tables appear one by one, its meta row last): a table of another name, or a
    meta table holding rows but no schema_version, or of other columns. Why: any file with a table named meta (a
    common name) beside its own was taken for a store, and the store's tables were added to it (an audit)."""
    tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if {table for table in tables - STORE_TABLES if not table.startswith("sqlite_")}:
        return f"tables {', '.join(sorted(tables))}"
    if "meta" in tables:
        try:
            keys = {str(row[0]) for row in connection.execute("SELECT key FROM meta")}
        except sqlite3.OperationalError:
            return "a meta table of other columns"
        if keys and "schema_version" not in keys:
            return f"a meta table of keys {', '.join(sorted(keys)[:5])}, no schema_version"
    return None


def check_schema_version(path: Path, version: str | None, expected: int) -> None:
    """Raise :class:`InputError` naming ``db`` unless the store's ``version`` is ``expected``: a store of a newer
    svs-depth says so (it was "has schema version 3, expected 2"), one without a version says so (it was "schema
    version None"), and a version that is no number is refused (it was an internal error)."""
    if version is not None and str(version).strip().isdigit() and int(version) == expected:
        return
    if version is None:
        raise InputError(f"db: {path} is not a results store (its meta table has no schema_version)")
    if not str(version).strip().isdigit():
        raise InputError(f"db: {path} is not a results store (schema_version {version!r} is not a number)")
    newer = int(version) > expected
    raise InputError(f"db: {path} has schema version {int(version)}, expected {expected}"
                     + ("; it was written by a newer svs-depth: update this one, or name another file" if newer
                        else ""))


def check_store_path(path: str | Path, create: bool) -> Path:
    """``path`` as a results store's file (``create``: one that may be made), checked by its name alone, before
    sqlite or any import of the pipeline (``svs-depth results missing.sqlite`` said so after torch's 2 s import)."""
    check_path_given(path, "db", "a results file name")  # ('' is '.': "got a folder: .", an audit)
    path = Path(path)
    kind = path_kind(path, "db")
    if kind in ("folder", "other") or (kind == "missing" and not create):
        # A device too: --db /dev/null failed only after sqlite had made /dev/null-journal.
        got = {"folder": "a folder", "other": "a device or other special file", "missing": "no file"}[kind]
        raise InputError(f"db: expected a results file, got {got}: {path}")
    if path.is_symlink() and kind == "missing":  # its cleanup deleted the user's link (an audit)
        raise InputError(f"db: {path} is a link to {os.path.realpath(path)}, which does not exist")
    if create and path.parent and not path.parent.is_dir():
        raise InputError(f"db: the folder {path.parent} does not exist" if not path.parent.exists()
                         else f"db: {path.parent} is a file, not a folder")
    if create:  # WAL keeps its journal beside the file: else sqlite's "unable to open" would call it no store
        # (beside a link's target: a link to a store on a read-only share was "unable to open", an audit)
        check_writable_folder(Path(os.path.realpath(path)).parent if path.is_symlink() else path.parent, "db")
    return path


def raise_if_disk_failed(error: sqlite3.DatabaseError, path: Path) -> None:
    """An :class:`OSError` naming the store for SQLite's full disk or I/O error, or a lock another process kept
    past :data:`BUSY_TIMEOUT_S` (the run's failure, exit 1, as an export's: a full disk read as "not a results
    store", a usage error, or as an internal error)."""
    code = getattr(error, "sqlite_errorcode", 0) & 0xFF  # the primary code of an extended one
    if code in (SQLITE_FULL, SQLITE_IOERR):
        raise OSError(errno.ENOSPC if code == SQLITE_FULL else errno.EIO,
                      f"db: cannot write {path}: {error}") from None
    if code in (SQLITE_BUSY, SQLITE_LOCKED):  # it was "not a results store (database is locked)", exit 2
        raise OSError(errno.EBUSY, f"db: {path}: another process has kept it locked for over {BUSY_TIMEOUT_S:g} s (a "
                                   "write it has not ended: another program with it open?); run again once that "
                                   "has ended (what is stored is kept)") from None


def while_locked(connection: sqlite3.Connection, path: Path, step: Callable[[], _Result]) -> _Result:
    """``step()`` (statements on ``connection`` that take the write lock of the store ``path``), tried again while
    another connection holds it, up to :data:`BUSY_TIMEOUT_S` in all; then SQLite's SQLITE_BUSY error is raised
    (:func:`raise_if_disk_failed` names it). SQLite waits :data:`BUSY_SLICE_S` at a time, this function sleeps in
    between, so a Ctrl-C or SIGTERM ends the wait at once; past :data:`BUSY_NOTICE_S` the wait is said once (a
    RuntimeWarning). ``step`` must be safe to run again after it failed on the lock (a transaction's first
    statement, or statements that change nothing twice)."""
    started, said = time.monotonic(), False
    connection.execute(f"PRAGMA busy_timeout = {round(BUSY_SLICE_S * 1000)}")
    try:
        while True:
            try:
                return step()
            except sqlite3.OperationalError as error:
                waited = time.monotonic() - started
                if getattr(error, "sqlite_errorcode", 0) & 0xFF not in (SQLITE_BUSY, SQLITE_LOCKED) \
                        or waited + BUSY_SLICE_S >= BUSY_TIMEOUT_S:
                    raise
                if not said and waited >= BUSY_NOTICE_S:
                    said = True
                    warnings.warn(f"db: {path} is locked by another process's write; waiting up to "
                                  f"{BUSY_TIMEOUT_S:g} s for it to end", RuntimeWarning, stacklevel=2)
                time.sleep(BUSY_SLICE_S)
    finally:
        connection.execute(f"PRAGMA busy_timeout = {round(BUSY_TIMEOUT_S * 1000)}")
