"""What a resumed sweep says of the rows it keeps and does not run again (:func:`kept_rows_notices`): rows computed
by another code version, and rows of pairs whose files changed since they were stored. A sweep runs only what a
store lacks, so a sweep run again after a code change or a mended image said "N rows already in DB, 0 to run" and
no more, its whole table perhaps the old code's or the old files' (an audit)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

__all__ = ["changed_files_notice", "kept_rows_notices", "other_versions_notice"]


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


def _files_of(path: str | None) -> Iterator[Path]:
    """The files a stored pair's ``left`` or ``right`` names: the file, or a scene folder's own files (its images,
    calibration and ground truth; an image overwritten in place leaves the folder's own time as it was)."""
    if not path:
        return
    folder = Path(path)
    if folder.is_dir():
        yield from (entry for entry in folder.iterdir() if entry.is_file())
    else:
        yield folder


def _newest_change(left: str | None, right: str | None) -> float | None:
    """The latest modification time of a pair's files, or None where none can be read (a pair since removed: it
    is a bad pair of this sweep, said as such)."""
    times = []
    for file in (*_files_of(left), *_files_of(right)):
        try:
            times.append(os.stat(file).st_mtime)
        except OSError:
            continue
    return max(times, default=None)


def changed_files_notice(store, db, kept: set[tuple[str, str]]) -> str | None:
    """How many of the ``kept`` rows are of pairs a file of which changed after the run that stored the row
    started (a mended image, a corrected ground truth), naming the first; None where none did."""
    from .store import _canonical_ids

    canonical, newest, changed, names = _canonical_ids(), {}, 0, []
    for config_id, pair_id, left, right, started, name in store.connection.execute(
            "SELECT r.config_id, r.pair_id, p.left, p.right, u.started_unix_s, p.name FROM results r "
            "JOIN pairs p USING (pair_id) LEFT JOIN runs u USING (run_id)"):
        if (config_id, canonical(pair_id)) not in kept or started is None:
            continue
        if pair_id not in newest:
            newest[pair_id] = _newest_change(left, right)
        if newest[pair_id] is not None and newest[pair_id] > started:
            changed += 1
            if name not in names:
                names.append(name)
    if not changed:
        return None
    return (f"{changed} of the {len(kept)} rows this sweep keeps in {db} are of pairs whose files changed since the "
            f"row was stored ({', '.join(names[:3])}{f' and {len(names) - 3} more' if len(names) > 3 else ''}) and "
            f"are not run again (a new --db runs them on the files as they are now)")
