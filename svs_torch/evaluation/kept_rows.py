"""What a resumed sweep says of the rows it keeps and does not run again (:func:`kept_rows_notices`): rows computed
by another code version, and rows of pairs whose files changed since they were stored (which ``svs-depth results``
notes too). A sweep runs only what a store lacks, so a sweep run again after a code change or a mended image said
"N rows already in DB, 0 to run" and no more, its whole table perhaps the old code's or the old files' (an audit).
A file's change is its modification time after the start of the run that stored the row: a copy that does not keep
the times (``cp -r`` without ``-p``) reads as changed."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

__all__ = ["changed_files_notice", "kept_rows_notices", "named", "other_versions_notice",
           "rows_of_changed_files"]


def kept_rows_notices(store, db, kept: set[tuple[str, str]], version: str, adding: bool) -> list[str]:
    """The warnings of a sweep of code ``version`` on the :class:`~.store.ResultStore` ``db`` that keeps the rows
    ``kept`` ((config_id, pair_id), pair ids canonical) and, where ``adding``, writes others."""
    notices = (other_versions_notice(store, db, kept, version, adding), changed_files_notice(store, db, kept))
    return [notice for notice in notices if notice]


def other_versions_notice(store, db, kept: set[tuple[str, str]], version: str, adding: bool) -> str | None:
    """How many of the ``kept`` rows code versions other than ``version`` wrote, or, where it keeps none of theirs
    but adds rows (``adding``), that the store holds some; None where there is nothing to say."""
    from .store import _canonical_ids

    previous = [v for v in store.code_versions() if v != version]
    if not previous:
        return None
    canonical, counts = _canonical_ids(), {}
    for config_id, pair_id, written_by in store.connection.execute(
            "SELECT r.config_id, r.pair_id, u.code_version FROM results r LEFT JOIN runs u USING (run_id)"):
        if written_by != version and (config_id, canonical(pair_id)) in kept:
            counts[str(written_by)] = counts.get(str(written_by), 0) + 1
    if counts:
        return (f"{sum(counts.values())} of the {len(kept)} rows this sweep keeps in {db} were computed by other "
                f"code versions ({', '.join(counts)}) and are not run again; this run is {version} (a new --db runs "
                f"every row with it)")
    return (f"{db} holds rows from other code versions ({', '.join(previous)}); this run is {version}" if adding
            else None)


def _files_of(path: str) -> Iterator[Path]:
    """The files one path of a stored pair names: the file, or a scene folder's own files (its images, calibration
    and ground truth; an image overwritten in place leaves the folder's own time as it was)."""
    folder = Path(path)
    if not folder.is_dir():
        yield folder
        return
    try:
        entries = list(folder.iterdir())
    except OSError:  # a folder this user may no longer list: nothing to compare
        return
    yield from (entry for entry in entries if entry.is_file())


def _newest_change(pair_id: str) -> float | None:
    """The latest modification time of a stored pair's files (its id's absolute paths, not its ``left``, which may
    be relative to the folder a run was started in), or None where none can be read (a bad list line's; a pair
    since removed, a bad pair of a run now, said as such)."""
    if pair_id.startswith("bad:"):
        return None
    times = []
    for part in pair_id.split("|"):
        for file in () if part.startswith("f=") else _files_of(part):
            try:
                times.append(os.stat(file).st_mtime)
            except OSError:
                continue
    return max(times, default=None)


def rows_of_changed_files(store, kept: set[tuple[str, str]] | None = None) -> tuple[int, int, list[str]]:
    """Of the store's rows (or of ``kept``, (config_id, pair_id) with pair ids canonical): how many are of pairs a
    file of which changed after the run that stored the row started (a mended image, a corrected ground truth),
    how many were looked at, and the names of those pairs."""
    from .store import _canonical_ids

    canonical, newest, changed, seen, names = _canonical_ids(), {}, 0, 0, []
    for config_id, pair_id, started, name in store.connection.execute(
            "SELECT r.config_id, r.pair_id, u.started_unix_s, p.name FROM results r JOIN pairs p USING (pair_id) "
            "LEFT JOIN runs u USING (run_id)"):
        if kept is not None and (config_id, canonical(pair_id)) not in kept:
            continue
        seen += 1
        if pair_id not in newest:
            newest[pair_id] = _newest_change(pair_id)
        if started is not None and newest[pair_id] is not None and newest[pair_id] > started:
            changed += 1
            if name not in names:
                names.append(name)
    return changed, seen, names


def named(names: list[str]) -> str:
    """The first three ``names``, and how many more."""
    return f"{', '.join(names[:3])}{f' and {len(names) - 3} more' if len(names) > 3 else ''}"


def changed_files_notice(store, db, kept: set[tuple[str, str]]) -> str | None:
    """How many of the ``kept`` rows :func:`rows_of_changed_files` finds, naming their pairs; None where none."""
    changed, _, names = rows_of_changed_files(store, kept)
    if not changed:
        return None
    return (f"{changed} of the {len(kept)} rows this sweep keeps in {db} are of pairs whose files changed since the "
            f"row was stored ({named(names)}) and are not run again (a new --db runs them on the files as they are "
            f"now)")
