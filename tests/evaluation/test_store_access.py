"""The results store's access: sweeps of different configurations hold them together, one of the same is refused
(tests/evaluation/test_sweep.py has it across processes); a read-only store and one of another schema are
refused in words of the store."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import pytest

from svs_torch.core.checks import InputError
from svs_torch.evaluation.store import ResultStore
from svs_torch.evaluation.store_access import sweep_is_writing

OFD_LOCKS = os.name == "posix" and hasattr(__import__("fcntl"), "F_OFD_SETLK")


@pytest.mark.skipif(not OFD_LOCKS, reason="needs open-file-description locks (Linux)")
def test_claims_of_other_configurations_are_taken_beside_and_the_same_refused(tmp_path):
    db = tmp_path / "store.sqlite"
    with ResultStore(db) as first, ResultStore(db) as second, ResultStore(db) as third:
        first.claim_for_a_sweep(["a", "b"])
        second.claim_for_a_sweep(["c"])  # another grid: no refusal
        with pytest.raises(InputError, match=rf"^db: another run \(a sweep or an eval --db\) is writing {db} and "
                                             r"running 1 of this run's 2 configurations; run this one once it has ended "
                                             r"\(it then runs only"):
            third.claim_for_a_sweep(["d", "b"])
        assert sweep_is_writing(db)
        first.close()
        third.claim_for_a_sweep(["d", "b"])  # released with the store
    assert not sweep_is_writing(db)


@pytest.mark.skipif(not OFD_LOCKS, reason="emulates the BSDs' flock with open-file-description locks (Linux)")
def test_without_ofd_locks_one_sweep_holds_the_store_and_its_own_sqlite_locks_do_not_refuse_it(tmp_path, monkeypatch):
    """Without OFD locks (macOS) a sweep held the whole store with ``flock`` on the store itself. On the BSDs flock
    and SQLite's record locks on a file are one list (Linux keeps them apart, so it is emulated here by a
    whole-file OFD lock, which conflicts with record locks as a BSD flock does): the store's own open connection
    refused every sweep as "another sweep is writing". Now the claim is a flock on a file beside the store."""
    import fcntl
    import struct

    setlk, setlkw = fcntl.F_OFD_SETLK, fcntl.F_OFD_SETLKW

    def bsd_flock(fd, operation):
        kind = fcntl.F_UNLCK if operation & fcntl.LOCK_UN else fcntl.F_WRLCK
        command = setlk if operation & (fcntl.LOCK_NB | fcntl.LOCK_UN) else setlkw
        fcntl.fcntl(fd, command, struct.pack("hhqqi4x", kind, 0, 0, 0, 0))

    monkeypatch.setattr(fcntl, "flock", bsd_flock)
    monkeypatch.delattr(fcntl, "F_OFD_SETLK")
    db = tmp_path / "store.sqlite"
    with ResultStore(db) as first, ResultStore(db) as second:
        first.claim_for_a_sweep(["a"])
        first.start_run("sweep", "v", {}, "")  # its own writes go on
        with pytest.raises(InputError, match=rf"^db: another run \(a sweep or an eval --db\) is writing {db}; run "
                           "this one once it has ended"):
            second.claim_for_a_sweep(["b"])
        first.close()
        second.claim_for_a_sweep(["b"])  # released with the store


def test_a_read_only_store_is_named_read_only_not_another_file(tmp_path, monkeypatch):
    """Found by an audit: a store SQLite may not write (its permissions; simulated, as root writes anywhere) was
    "not a results store (attempt to write a readonly database)"."""
    from svs_torch.evaluation import store as store_module

    db = tmp_path / "kept.sqlite"
    ResultStore(db).close()
    connect = sqlite3.connect

    def read_only(database, *args, **kwargs):
        return connect(f"{Path(database).resolve().as_uri()}?mode=ro", *args, **{**kwargs, "uri": True})

    monkeypatch.setattr(store_module.sqlite3, "connect", read_only)
    with pytest.raises(InputError, match=f"^db: cannot write {db}: the file is read-only"):
        ResultStore(db)


@pytest.mark.parametrize("version, expected", [
    ("two", r"is not a results store \(schema_version 'two' is not a number\)$"),
    (None, r"is not a results store \(its meta table has no schema_version\)$"),
    ("3", r"has schema version 3, expected 2; it was written by a newer svs-depth: update this one"),
])
def test_a_store_of_another_schema_is_refused_in_one_line(tmp_path, version, expected):
    """Found by an audit: a version that is no number was an internal error (ValueError), a missing one read
    "schema version None", a newer one did not say it was newer."""
    db = tmp_path / "other.sqlite"
    ResultStore(db).close()
    with sqlite3.connect(db) as connection:
        connection.execute("DELETE FROM meta")
        if version is not None:
            connection.execute("INSERT INTO meta VALUES ('schema_version', ?)", (version,))
    connection.close()
    for create in (False, True) if version is not None else (False,):  # (to write, a versionless one gets it)
        with pytest.raises(InputError, match=f"^db: {db} " + expected):
            ResultStore(db, create=create)


def test_a_store_another_process_keeps_locked_is_named_busy_not_another_file(tmp_path, monkeypatch, capsys, data_dir):
    """Found by an audit: a store another program kept in a write transaction for over the 60 s wait (a database
    browser, a script) was "db: FILE is not a results store (database is locked)", exit 2, for sweep and eval
    --db. (The wait is cut to 0.1 s here.)"""
    from svs_torch.cli import main
    from svs_torch.evaluation import store_access

    db = tmp_path / "busy.sqlite"
    ResultStore(db).close()
    monkeypatch.setattr(store_access, "BUSY_TIMEOUT_S", 0.1)
    other = sqlite3.connect(db, isolation_level=None)
    try:
        other.execute("BEGIN IMMEDIATE")
        other.execute("DELETE FROM runs")
        teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
        assert main(["eval", str(teddy), "--size", "160x120", "--db", str(db)]) == 1
        assert capsys.readouterr().err.strip().endswith(
            f"error: --db: {db}: another process has kept it locked for over 0.1 s (a write it has not ended: "
            "another program with it open?); run again once that has ended (what is stored is kept)")
        other.execute("ROLLBACK")
        with ResultStore(db) as store:  # opened, then locked by the other mid-run: the write says so
            other.execute("BEGIN IMMEDIATE")
            with pytest.raises(OSError, match=f"db: {db}: another process has kept it locked for over 0.1 s"):
                store.start_run("eval", "v", {}, "")
    finally:
        other.close()


def test_a_store_on_a_file_system_without_locks_is_not_said_to_be_held(tmp_path, monkeypatch):
    """A file system that takes no locks (ENOLCK: some network mounts) was "another sweep is writing FILE" with
    no other sweep; now nothing is held there and nothing refused."""
    import errno
    import fcntl

    def no_locks(*args):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "fcntl", no_locks)
    monkeypatch.setattr(fcntl, "flock", no_locks)
    db = tmp_path / "nfs.sqlite"
    with ResultStore(db) as first, ResultStore(db) as second:
        first.claim_for_a_sweep(["a"])
        second.claim_for_a_sweep(["a"])


def test_a_link_to_a_store_in_a_folder_that_takes_no_files_names_that_folder(tmp_path, refuse_creating_in):
    """Found by an audit: --db a link (in a writable folder) to a store on a read-only share was "db: LINK is not
    a results store (unable to open database file)": SQLite keeps its journal beside the link's target. (The
    read-only folder is simulated: root writes anywhere.)"""
    share = tmp_path / "share"
    share.mkdir()
    ResultStore(share / "store.sqlite").close()
    link = tmp_path / "store.sqlite"
    link.symlink_to(share / "store.sqlite")
    refuse_creating_in(share, 30, "Read-only file system")
    with pytest.raises(InputError, match=rf"^db: cannot write in folder '{share}' \(Read-only file system\)$"):
        ResultStore(link)
    with ResultStore(link, create=False) as store:  # read, it is as it was
        assert store.configs() == []


def test_a_store_being_written_read_from_a_folder_that_takes_no_files_says_why(tmp_path, capsys,
                                                                                store_folder_not_writable):
    """Found by an audit: a store with rows still in its -wal file (a colleague's sweep writing it on a share)
    read from a folder this user cannot write was "db: FILE is not a results store (unable to open database
    file)". (The refusal is simulated, as in test_sweep's read of a cleanly closed store: root writes anywhere.)"""
    from svs_torch.cli import main

    db = tmp_path / "shared.sqlite"
    ResultStore(db).close()
    Path(f"{db}-wal").write_bytes(b"")  # a writer's rows not yet in the file
    store_folder_not_writable()
    assert main(["results", str(db)]) == 2
    assert capsys.readouterr().err.strip().endswith(
        f"error: FILE.sqlite: cannot read {db} from here yet: rows are still in shared.sqlite-wal (a sweep writing "
        "it, or one killed), and reading them needs a file made in its folder, which this user cannot write; read it "
        "once the writer has ended, or copy both files to a folder you can write")


def test_a_pair_whose_path_is_not_utf8_is_refused_by_eval_db_before_the_store_is_made(tmp_path, capsys, data_dir):
    """An audit: 'eval SCENE --db FILE' where the scene folder's name holds bytes of another encoding (Latin-1, read
    as surrogates) ended in "internal error: UnicodeEncodeError ... surrogates not allowed", exit 1, with FILE made
    and holding no pair. A store keeps paths as UTF-8 text: now one line naming the path, exit 2, no FILE."""
    import shutil

    from svs_torch.cli import main

    scene = tmp_path / os.fsdecode(b"Ted\xffdy")
    shutil.copytree(data_dir / "middlebury_eval3_Q" / "Teddy", scene)
    db = tmp_path / "r.sqlite"
    assert main(["eval", str(scene), "--size", "80x60", "--db", str(db)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("svs-depth eval: error: --db: ") and "Ted\\udcffdy" in error and "UTF-8" in error
    assert "\n" not in error and not db.exists()


def test_a_command_line_that_is_not_utf8_is_recorded_escaped(tmp_path):
    """An audit: 'eval SCENE --db $'r\\xff.sqlite'' ended in an internal UnicodeEncodeError when the store recorded
    the command line; the record escapes the bytes, as the messages show them."""
    with ResultStore(tmp_path / "r.sqlite") as store:
        run_id = store.start_run("eval", "v", {}, "eval x --db r\udcff.sqlite")
        assert store.connection.execute("SELECT sweep FROM runs WHERE run_id = ?", (run_id,)).fetchone() == (
            "eval x --db r\\udcff.sqlite",)
