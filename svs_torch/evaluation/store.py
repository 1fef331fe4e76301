"""The results store of ``svs-depth sweep`` and ``eval --db``: one SQLite file (standard library ``sqlite3``).

Why SQLite: in WAL mode, with one transaction per task and ``INSERT OR IGNORE`` on a unique (configuration,
pair) key, a sweep killed at any moment (even SIGKILL) keeps every committed task and nothing half-written; a
restart runs only the missing rows and can never duplicate one. Only a sweep's parent process writes (workers
return rows); sweeps of different configurations (and ``eval --db``) may write one store at once, SQLite taking
their short transactions in turn (each waits up to 60 s for another's); a sweep whose configurations another
running sweep holds is refused (:mod:`.store_access`). Readers (``svs-depth results``) never block a writer.

Schema (``schema_version`` 2: version 1 had no ``calibration`` column)::

    meta(key TEXT PRIMARY KEY, value TEXT)            -- schema_version
    configs(config_id TEXT PRIMARY KEY,               -- sha256 of {"config": the whole PipelineConfig, "size"}
            label TEXT,                               -- the overrides as "key=value ..." ("(preset)" if none;
                                                      -- " | " between the descriptions of one configuration)
            preset TEXT,                              -- "default" or "paper": what the overrides apply to
            overrides TEXT,                           -- JSON {dotted key: value}
            size TEXT,                                -- "320x240", or "native"
            config TEXT)                              -- JSON of the whole PipelineConfig
    pairs(pair_id TEXT PRIMARY KEY,                   -- absolute paths (+ listed calibration), or "bad:<reason>"
          name TEXT, left TEXT, right TEXT, scene INTEGER, calibration TEXT)  -- calibration: JSON or NULL
    runs(run_id INTEGER PRIMARY KEY AUTOINCREMENT, started_unix_s REAL, command TEXT,
         code_version TEXT,                           -- git commit (+"-dirty") or the package version
         environment TEXT,                            -- JSON: python, torch, numpy, opencv, platform, CPUs,
                                                      -- executor, workers, threads per worker
         sweep TEXT)                                  -- the sweep file's text (or the eval's arguments)
    results(config_id TEXT NOT NULL REFERENCES configs, pair_id TEXT NOT NULL REFERENCES pairs,
            run_id INTEGER REFERENCES runs,
            <one column per PairEvaluation field: name, status, reason, calibrated, calibration (JSON), has_truth,
             r_min_m, r_max_m, real_r_min_m, real_r_max_m, acc_r_min_pct, acc_r_max_pct, acc_objects_pct, num_objects,
             dense_error_median_px, dense_within_1px, dense_within_3px, dense_num_px, sparse_error_median_px,
             sparse_within_1px, sparse_within_3px, inlier_precision, sparse_num_points, num_keypoints_left,
             num_keypoints_right, num_matches, num_inliers, rectified, time_s, metric_px_scale, the stereo
             metrics <scope>_<metric> for scope map_all, map_nocc, kept_all, kept_nocc and metric density,
             bad0_5_pct, bad1_pct, bad2_pct, bad4_pct, avgerr_px, rms_px, a50_px, a90_px, a95_px, a99_px,
             d1_pct, num_px (stereo_metrics.py), objects (JSON list)>,
            UNIQUE(config_id, pair_id))

A file made before a result column existed gets it (NULL in its older rows) when opened to write; opened to
read, it is left as it is and its rows read None there.

Units are in the column names (``_m`` metres, ``_px`` pixels, ``_pct`` percent, ``_s`` seconds; ``within_*``
and ``inlier_precision`` are shares in [0, 1]); booleans are 0/1; a metric that does not exist is NULL.
Everything but ``time_s`` and ``run_id`` is deterministic: a resumed sweep's rows equal an uninterrupted one's.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sqlite3
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from ..core.checks import InputError
from .metrics import UNRUN_STATUSES, PairEvaluation
from .overrides import merge_labels
from . import store_access
from .store_access import (SQLITE_CANTOPEN, SQLITE_READONLY, check_schema_version, check_store_path, claim_configs,
                           foreign_tables, raise_if_disk_failed, read_only_error, unreadable_beside_writer,
                           while_locked)

__all__ = ["RESULT_COLUMNS", "RETRIED_STATUSES", "SCHEMA_VERSION", "ResultStore", "check_storable"]

SCHEMA_VERSION = 2
#: Stored statuses a resumed run retries, those of the pairs the pipeline did not run on (a pipeline that raised, and
#: a pair whose files could not be read or were too small when it ran: since added, mended or replaced, perhaps).
RETRIED_STATUSES = UNRUN_STATUSES
_RETRIED_SQL = "(" + ", ".join(f"'{status}'" for status in RETRIED_STATUSES) + ")"

_SQL_TYPES = {"str": "TEXT", "bool": "INTEGER", "int": "INTEGER", "float": "REAL", "list": "TEXT", "dict": "TEXT"}


def _column_type(annotation: str) -> str:
    base = annotation.split("|")[0].strip().split("[")[0]
    return _SQL_TYPES[base]


#: ``(name, SQL type)`` of the per-pair result columns, in PairEvaluation's order.
RESULT_COLUMNS: tuple[tuple[str, str], ...] = tuple(
    (f.name, _column_type(str(f.type))) for f in dataclasses.fields(PairEvaluation))

_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta(key TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS configs(config_id TEXT PRIMARY KEY, label TEXT, preset TEXT, overrides TEXT, size TEXT,
                                   config TEXT);
CREATE TABLE IF NOT EXISTS pairs(pair_id TEXT PRIMARY KEY, name TEXT, left TEXT, right TEXT, scene INTEGER,
                                 calibration TEXT);
CREATE TABLE IF NOT EXISTS runs(run_id INTEGER PRIMARY KEY AUTOINCREMENT, started_unix_s REAL, command TEXT,
                                code_version TEXT, environment TEXT, sweep TEXT);
CREATE TABLE IF NOT EXISTS results(
    config_id TEXT NOT NULL REFERENCES configs(config_id),
    pair_id TEXT NOT NULL REFERENCES pairs(pair_id),
    run_id INTEGER REFERENCES runs(run_id),
    {", ".join(f'"{name}" {kind}' for name, kind in RESULT_COLUMNS)},
    UNIQUE(config_id, pair_id));
"""


def _to_sql(value: Any) -> Any:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return value


def check_storable(db: str | os.PathLike, sources: Iterable[Any]) -> str | os.PathLike:
    """``db`` once every pair of ``sources`` has paths a store can keep: UTF-8 text, which SQLite's text is. Why: a
    scene folder whose name holds bytes of another encoding (Latin-1, read as surrogates) ended eval --db in "internal
    error: UnicodeEncodeError", the store made and holding no pair (an audit). Checked before the store is opened."""
    from ..core.files import display_path

    for source in sources:
        for text in (source.left, source.right, source.name, source.pair_id):
            try:
                (text or "").encode("utf-8")
            except UnicodeEncodeError:
                raise InputError(f"db: cannot record {display_path(text)}: a results store keeps paths as UTF-8 "
                                 "text, and this name holds bytes of another encoding; rename it, or run without "
                                 "a store") from None
    return db


class ResultStore:
    """An open results store (see the module docstring); a context manager that closes it."""

    def __init__(self, path: str | Path, create: bool = True) -> None:
        self.path = check_store_path(path, create)
        new = create and not self.path.exists()
        size = self.path.stat().st_size if self.path.is_file() else None
        # SQLite takes a file shorter than its 100-byte header for an empty database and writes the tables into it:
        # a 1-byte text file named by --db became a store.
        if size is not None and 0 < size < 100:
            raise InputError(f"db: {self.path} is not a results store (not an SQLite file: {size} "
                             f"byte{'' if size == 1 else 's'}){': name a new file' if create else ''}")
        try:
            self.connection = self._connect_to_write() if create else self._connect_to_read()
            version = self.connection.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        except sqlite3.DatabaseError as error:
            if new:  # a store that could not be made is not left behind, nor its journal
                for leftover in (self.path, Path(f"{self.path}-wal"), Path(f"{self.path}-shm")):
                    leftover.unlink(missing_ok=True)
            raise_if_disk_failed(error, self.path)
            if getattr(error, "sqlite_errorcode", 0) & 0xFF == SQLITE_READONLY:
                raise read_only_error(self.path) from None
            # In words of the store, the same for sweep, eval --db and results (sqlite's were "file is not a
            # database", "no such table: meta").
            reason = ("not an SQLite file" if "file is not a database" in str(error) else "an empty file" if size == 0
                      else "an SQLite file without a results store's tables" if "no such table" in str(error)
                      else str(error))
            raise InputError(f"db: {self.path} is not a results store ({reason})") from None
        if version is not None and str(version[0]).strip() == "1":  # version 1 lacks only the calibration column
            version = self._from_version_1(create)
        check_schema_version(self.path, version and version[0], SCHEMA_VERSION)
        if create:
            self._add_missing_columns()

    def _connect_to_write(self) -> sqlite3.Connection:
        """The store opened to write, its tables made if it is new. Another program's SQLite file is refused before
        anything is written to it (a mistyped --db added the store's tables beside its own)."""
        # isolation_level=None: transactions are explicit (BEGIN IMMEDIATE … COMMIT), one per task.
        connection = sqlite3.connect(self.path, timeout=store_access.BUSY_TIMEOUT_S, isolation_level=None)
        foreign = foreign_tables(connection)
        if foreign:
            connection.close()
            raise InputError(f"db: {self.path} is another program's SQLite file ({foreign}), not a results store: "
                             f"name a new file")

        def make() -> None:  # each statement changes nothing run twice (a wait on another's lock runs it again)
            connection.execute("PRAGMA journal_mode=WAL")
            # NORMAL in WAL mode: a committed transaction survives a crash of the process (only a power cut may lose
            # the last ones), at a fraction of FULL's fsyncs.
            connection.execute("PRAGMA synchronous=NORMAL")
            connection.executescript(_SCHEMA)
            connection.execute("INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))

        try:
            while_locked(connection, self.path, make)
        except BaseException:
            connection.close()
            raise
        return connection

    def _connect_to_read(self) -> sqlite3.Connection:
        """The store opened to read, the file left as it is (a read turned another program's file into WAL mode
        before). A WAL store needs its folder writable even to be read (its shared-memory file); in a folder that
        is not (an archive, a colleague's share), a store closed cleanly (no ``-wal`` file beside it) is read as
        an immutable file. (Not ``mode=ro`` first: in a writable folder it would leave an empty ``-wal`` and a
        ``-shm`` file behind, which only a writer removes.)"""
        try:
            connection = sqlite3.connect(self.path, timeout=store_access.BUSY_TIMEOUT_S, isolation_level=None)
            connection.execute("SELECT name FROM sqlite_master").fetchall()
            return connection
        except sqlite3.OperationalError as error:
            if Path(f"{self.path}-wal").exists():  # rows not yet in the file: immutable would not see them
                if getattr(error, "sqlite_errorcode", SQLITE_CANTOPEN) & 0xFF in (SQLITE_CANTOPEN, SQLITE_READONLY):
                    raise InputError(unreadable_beside_writer(self.path)) from None  # was "not a results store"
                raise
        uri = f"{self.path.resolve().as_uri()}?mode=ro&immutable=1"
        return sqlite3.connect(uri, uri=True, isolation_level=None)

    def _add_missing_columns(self) -> None:
        """Result columns added since the file was made (e.g. the stereo metrics) are added, NULL in the rows
        stored before them: those rows were never measured so, and NULL is what a missing metric is. (Opened to
        read, the file is left as it is and :meth:`results` gives None for them.)"""
        present = {row[1] for row in self.connection.execute("PRAGMA table_info(results)")}
        missing = [(name, kind) for name, kind in RESULT_COLUMNS if name not in present]
        if missing:
            self._transaction((f'ALTER TABLE results ADD COLUMN "{name}" {kind}', ()) for name, kind in missing)

    def _from_version_1(self, create: bool) -> tuple[str]:
        """A version-1 store: opened to write, it gains the (empty) calibration column and becomes version 2;
        opened to read, it is read as it is (its rows have no calibration)."""
        if create:
            self._transaction([('ALTER TABLE results ADD COLUMN "calibration" TEXT', ()),
                               ("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION),))])
        return (str(SCHEMA_VERSION),)

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.connection.close()
        claim = getattr(self, "_claim", None)
        if claim is not None:  # its lock goes with it
            claim.close()
            self._claim = None

    def claim_for_a_sweep(self, config_ids: Iterable[str]) -> None:
        """Hold ``config_ids`` in the store for this process's sweep or eval --db until it closes (the claims of
        :mod:`.store_access`): two sweeps on one store each ran every task, their rows right, the work done twice,
        without a word (an audit); two of different configurations run together.

        Raises:
            InputError: naming ``db``, where another process holds any of them."""
        self._claim = claim_configs(self.path, config_ids)

    def _transaction(self, statements: Iterable[tuple[str, Sequence[Any]]]) -> int | None:
        """Run ``statements`` as one transaction; the row id the last one inserted. SQLite's full disk or I/O
        error is an :class:`OSError` naming the store (:func:`~.store_access.raise_if_disk_failed`); the wait for
        another connection's write is :func:`~.store_access.while_locked`'s."""
        cursor = self.connection.cursor()
        try:
            while_locked(self.connection, self.path, lambda: cursor.execute("BEGIN IMMEDIATE"))
            for sql, values in statements:
                cursor.execute(sql, values)
            row_id = cursor.lastrowid
            cursor.execute("COMMIT")
            return row_id
        except BaseException as error:
            if self.connection.in_transaction:  # a full disk may have ended it already
                cursor.execute("ROLLBACK")
            if isinstance(error, sqlite3.DatabaseError):
                raise_if_disk_failed(error, self.path)
            raise

    def add_configs(self, configs: Iterable[dict]) -> None:
        """Record configurations (``config_id``, ``label``, ``preset``, ``overrides``, ``size``, ``config``). A
        configuration already stored under another description keeps its row and gains the new label
        (:func:`~.overrides.merge_labels`): a sweep whose ``max_ratio=0.8`` is the stored default is summarised
        under both names, not under the first sweep's alone."""
        configs = list(configs)
        stored = dict(self.connection.execute("SELECT config_id, label FROM configs").fetchall())
        statements = []
        for c in configs:
            key = c["config_id"]
            if key not in stored:
                stored[key] = c["label"]
                statements.append(("INSERT OR IGNORE INTO configs VALUES (?, ?, ?, ?, ?, ?)",
                                   (key, c["label"], c["preset"], json.dumps(c["overrides"]), c["size"],
                                    json.dumps(c["config"]))))
            elif (label := merge_labels(stored[key], c["label"])) != stored[key]:
                stored[key] = label
                statements.append(("UPDATE configs SET label = ? WHERE config_id = ?", (label, key)))
        self._transaction(statements)

    def add_pairs(self, pairs: Iterable[Any]) -> None:
        """Record :class:`~svs_torch.data.PairSource` entries, and forget the rows of a line of one of their lists
        that was bad when stored and is not now (mended or removed: its ``bad:`` id, which names the list and the
        line, no longer among them): a line whose typo was mended left a failed pair in every mean for ever."""
        pairs = list(pairs)
        current = {p.pair_id for p in pairs}
        lists = {p.list_file for p in pairs if getattr(p, "list_file", None)}
        stale = [pair_id for (pair_id,) in self.connection.execute("SELECT pair_id FROM pairs WHERE pair_id LIKE "
                                                                    "'bad:%'")
                 if pair_id not in current and any(f" of {name}: " in pair_id for name in lists)]
        self._transaction([*(("DELETE FROM results WHERE pair_id = ?", (pair_id,)) for pair_id in stale),
                           *(("DELETE FROM pairs WHERE pair_id = ?", (pair_id,)) for pair_id in stale),
                           *(("INSERT OR IGNORE INTO pairs VALUES (?, ?, ?, ?, ?, ?)",
                              (p.pair_id, p.name, p.left, p.right, int(p.scene),
                               json.dumps(p.calibration) if p.calibration else None)) for p in pairs)])

    def start_run(self, command: str, code_version: str, environment: dict, sweep: str) -> int:
        """Record a run; returns its ``run_id``."""
        # A command line's bytes of another encoding (surrogates) escaped, as messages show them: SQLite's text is
        # UTF-8, and 'eval ... --db $'r\\xff.sqlite'' ended in an internal UnicodeEncodeError (an audit).
        command, sweep = (text.encode("utf-8", "backslashreplace").decode("utf-8") for text in (command, sweep))
        return int(self._transaction([(
            "INSERT INTO runs(started_unix_s, command, code_version, environment, sweep) VALUES (?, ?, ?, ?, ?)",
            (time.time(), command, code_version, json.dumps(environment), sweep))]))

    def code_versions(self) -> list[str]:
        return [row[0] for row in self.connection.execute("SELECT DISTINCT code_version FROM runs ORDER BY run_id")]

    def done(self, config_ids: Sequence[str] | None = None, retried: bool = False) -> set[tuple[str, str]]:
        """The (config_id, pair_id) keys already stored, but those of rows with a :data:`RETRIED_STATUSES`
        status: a run that raised (out of memory, a full disk under an export), or a pair whose files were
        missing, unreadable or too small then, is run again when a sweep resumes (and its new row replaces the
        old one). ``retried``: those keys instead."""
        rows = self.connection.execute(f"SELECT config_id, pair_id FROM results WHERE status "
                                       f"{'IN' if retried else 'NOT IN'} {_RETRIED_SQL}")
        wanted = None if config_ids is None else set(config_ids)
        canonical = _canonical_ids()
        return {(c, canonical(p)) for c, p in rows if wanted is None or c in wanted}

    def stored_values(self, config_id: str, columns: Sequence[str]) -> dict[str, tuple]:
        """``{pair_id: (the row's values of columns)}`` of every row stored for ``config_id``; ``columns``: names
        of :data:`RESULT_COLUMNS` (a bool read back as 0 or 1)."""
        unknown = set(columns) - {name for name, _ in RESULT_COLUMNS}
        if unknown:
            raise ValueError(f"columns: expected result columns, got {sorted(unknown)}")
        names = ", ".join(f'"{name}"' for name in columns)
        canonical = _canonical_ids()
        rows = self.connection.execute(f"SELECT pair_id, {names} FROM results WHERE config_id = ?", (config_id,))
        return {canonical(pair_id): tuple(values) for pair_id, *values in rows}

    def write_task(self, config_id: str, run_id: int, rows: Sequence[tuple[str, PairEvaluation]]) -> int:
        """Store one task's ``(pair_id, evaluation)`` rows in one transaction; rows already present are kept as
        they are, but a row of a :data:`RETRIED_STATUSES` status, which a new result replaces. Returns the number
        of rows written."""
        names = ["config_id", "pair_id", "run_id"] + [name for name, _ in RESULT_COLUMNS]
        columns = ", ".join(f'"{name}"' for name in names)
        replace = ", ".join(f'"{name}" = excluded."{name}"' for name in names[2:])
        sql = (f"INSERT INTO results({columns}) VALUES ({', '.join('?' * len(names))}) ON CONFLICT(config_id, "
               f"pair_id) DO UPDATE SET {replace} WHERE results.status IN {_RETRIED_SQL}")
        before = self.connection.total_changes
        self._transaction((sql, [config_id, pair_id, run_id]
                           + [_to_sql(getattr(evaluation, name)) for name, _ in RESULT_COLUMNS])
                          for pair_id, evaluation in rows)
        return self.connection.total_changes - before

    def configs(self) -> list[dict]:
        """Every stored configuration, in insertion order, with its overrides decoded."""
        cursor = self.connection.execute("SELECT config_id, label, preset, overrides, size, config FROM configs "
                                         "ORDER BY rowid")
        return [{"config_id": c, "label": label, "preset": preset, "overrides": json.loads(overrides), "size": size,
                 "config": json.loads(config)} for c, label, preset, overrides, size, config in cursor]

    def results(self) -> list[dict]:
        """Every result row joined with its pair's ``left`` and ``right`` and the ``code_version`` of the run that
        wrote it, in a fixed order."""
        cursor = self.connection.execute(
            "SELECT r.*, p.left AS left, p.right AS right, u.code_version AS code_version FROM results r "
            "JOIN pairs p USING (pair_id) LEFT JOIN runs u USING (run_id) ORDER BY r.config_id, r.pair_id")
        names = [d[0] for d in cursor.description]
        rows = []
        for values in cursor:
            row = dict(zip(names, values))
            row["objects"] = json.loads(row["objects"]) if row["objects"] else []
            row["calibration"] = json.loads(row["calibration"]) if row.get("calibration") else None
            for name, _ in RESULT_COLUMNS:  # a column the file predates (opened to read): not measured
                row.setdefault(name, None)
            rows.append(row)
        return _latest_of_each_pair(rows)


def _canonical_ids():
    """A function from a stored pair id to the id of its files with symbolic links resolved (as
    :attr:`~svs_torch.data.PairSource.pair_id` writes them since): an id written through a link before names
    the same pair, and counts once. A bad list line's id (``bad:...``) stays."""
    cache: dict[str, str] = {}

    def canonical(pair_id: str) -> str:
        if pair_id not in cache:
            cache[pair_id] = pair_id if pair_id.startswith("bad:") else "|".join(
                part if part.startswith("f=") else os.path.realpath(part) for part in pair_id.split("|"))
        return cache[pair_id]
    return canonical


def _latest_of_each_pair(rows: list[dict]) -> list[dict]:
    """``rows`` with each (configuration, pair) once, its pair id made canonical (:func:`_canonical_ids`), the row
    of the latest run kept: one scene stored under two spellings (a folder and a link to it) weighed twice in every
    mean."""
    canonical, latest = _canonical_ids(), {}
    for row in rows:
        row["pair_id"] = canonical(row["pair_id"])
        key = (row["config_id"], row["pair_id"])
        if key not in latest or (row["run_id"] or 0) > (latest[key]["run_id"] or 0):
            latest[key] = row
    return sorted(latest.values(), key=lambda row: (row["config_id"], row["pair_id"]))
