"""svs-depth sweep: bad sweep files fail before any work; a sweep killed with SIGKILL resumes to the rows of an
uninterrupted run; Dask gives the same rows as the local process pool; svs-depth results reads them."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import svs_torch
from svs_torch.cli import main
from svs_torch.core.checks import InputError
from svs_torch.evaluation.sweep import load_sweep, plan_tasks, run_sweep
from svs_torch.pipeline import PipelineConfig

#: Four MiddEval3 scenes at 160x120, three configurations, one pair per task: 12 rows, 12 tasks.
SCENES = ("Teddy", "ArtL", "Piano", "Motorcycle")
SWEEP = """\
paths = [{paths}]
size = "160x120"
batch_size = 1
[grid]
"segmentation.kernel_size" = [3, 5, 7]
"""
TOTAL_ROWS = 12
#: Columns that legitimately differ between runs (wall time, which run wrote the row).
VOLATILE = ("time_s", "run_id")


def write_sweep(folder: Path, data_dir: Path, text: str = SWEEP) -> Path:
    paths = ", ".join(f'"{data_dir / "middlebury_eval3_Q" / name}"' for name in SCENES)
    path = folder / "sweep.toml"
    path.write_text(text.format(paths=paths))
    return path


@contextlib.contextmanager
def edited_copy(reference, db: Path):
    """The reference store copied to `db` and opened for edits in one transaction, closed on leaving."""
    shutil.copyfile(reference[1], db)
    connection = sqlite3.connect(db)
    try:
        with connection:
            yield connection
    finally:
        connection.close()


def stored_rows(db: Path) -> dict[tuple[str, str], dict]:
    connection = sqlite3.connect(db)
    connection.row_factory = sqlite3.Row
    try:
        rows = connection.execute("SELECT * FROM results").fetchall()
    finally:
        connection.close()
    return {(r["config_id"], r["pair_id"]): {k: r[k] for k in r.keys() if k not in VOLATILE} for r in rows}


def count_rows(db: Path) -> int:
    if not db.exists():
        return 0
    connection = sqlite3.connect(db, timeout=10)
    try:
        return connection.execute("SELECT count(*) FROM results").fetchone()[0]
    except sqlite3.OperationalError:  # the schema is not written yet
        return 0
    finally:
        connection.close()


@pytest.fixture(scope="module")
def reference(data_dir, tmp_path_factory) -> tuple[Path, Path]:
    """An uninterrupted sweep with the default executor (local process pool, two workers)."""
    folder = tmp_path_factory.mktemp("reference")
    sweep_file = write_sweep(folder, data_dir)
    outcome = run_sweep(load_sweep(sweep_file), folder / "reference.sqlite", workers=2, warn=pytest.fail)
    assert (outcome.tasks, outcome.rows_written) == (TOTAL_ROWS, TOTAL_ROWS)
    return sweep_file, folder / "reference.sqlite"


@pytest.mark.parametrize("text, message", [
    ('paths = ["."]\nsizes = "320x240"\n', "unknown key 'sizes' (did you mean size?"),
    ('paths = ["."]\nmax_ratoi = 0.7\n', "unknown key 'max_ratoi' (did you mean max_ratio? expected paths, size,"),
    ('paths = ["."]\n[grid]\n"segmentation.kernal_size" = [3]\n', "grid: unknown parameter 'segmentation.kernal_size'"),
    ('paths = ["."]\n[grid]\n"segmentation.kernel_size" = [3, 0]\n',
     "grid: segmentation.kernel_size = 0: kernel_size: expected a positive integer"),
    ('paths = ["."]\n[grid]\n"max_ratio" = ["high"]\n', "grid: max_ratio: expected a finite number, got 'high'"),
    ('paths = ["."]\n[grid]\n"max_ratio" = 0.6\n', "grid: max_ratio: expected a non-empty list of values"),
    ('paths = ["."]\n[set]\n"dense.window_size" = 8\n', "set: dense.window_size = 8: window_size: expected an odd"),
    ('paths = ["no/such/folder"]\n', "paths: no such file or folder"),
    # An audit: an empty path was the sweep file's own folder, swept for scenes.
    ('paths = [""]\n', "paths: expected a list of scene folders or pair lists, got ['']"),
    ('paths = ["."]\nsize = "320 by 240"\n', "size: expected WIDTHxHEIGHT"),
    ('paths = ["."]\npreset = "fast"\n', "preset: expected one of 'default', 'paper'"),
    ("paths = [\n", "not valid TOML"),
    # An audit: the grid's values ran and the fixed 0.7 never did, without a word.
    ('paths = ["."]\n[set]\nmax_ratio = 0.7\n[grid]\nmax_ratio = [0.6, 0.8]\n',
     "max_ratio: set both as fixed for every configuration and in [grid]; expected each in one of them"),
    # An audit of hostile files: each of these ran with one of the two values, or none, without a word.
    ('paths = ["."]\n[grid]\n"segmentation.kernel_size" = [7]\n[grid.segmentation]\nkernel_size = [3, 5]\n',
     "grid: segmentation.kernel_size: given twice (a quoted dotted key and a table's key name the same parameter)"),
    ('paths = ["."]\n"max_ratio" = 0.7\n[set]\nmax_ratio = 0.6\n',
     "max_ratio: given both at the top level and in [set]; expected each once"),
    ('paths = ["."]\n[set.exposure]\n', "set: exposure: expected true or false (on with its defaults, or off), got {}"),
    ('paths = ["."]\n[[configs]]\n"dense.window_size" = 5\n[configs.dense]\nwindow_size = 7\n',
     "configs[1]: dense.window_size: given twice"),
    # An audit: 2 [[configs]] over a grid of 5001 points made 10 002 configurations, past the grid's own limit.
    ('paths = ["."]\n[grid]\nseed = [' + ", ".join(map(str, range(5001)))
     + ']\n[[configs]]\n[[configs]]\nmax_ratio = 0.7\n',
     "configs: 2 [[configs]] x 5001 grid points = 10002 configurations, at most 10000"),
    # An audit: a preset that is a list or a table failed as "internal error: TypeError: unhashable type".
    ('paths = ["."]\npreset = ["paper"]\n', "preset: expected one of 'default', 'paper', got ['paper']"),
    ('paths = ["."]\n[[configs]]\npreset = {name = "paper"}\n',
     "configs[1]: preset: expected one of 'default', 'paper', got {'name': 'paper'}"),
    # An audit: arrays (or inline tables) nested 100 000 deep, or a table header of 5000 dotted parts, ended in
    # "internal error: RecursionError: maximum recursion depth exceeded" (the parser's, then flatten_table's).
    pytest.param('paths = ["."]\nseed = ' + "[" * 100_000 + "]" * 100_000 + "\n", "nested too deep", id="deep-arrays"),
    pytest.param('paths = ["."]\n[' + ".".join(["a"] * 5000) + "]\n", "nested too deep", id="deep-header"),
])
def test_bad_sweep_files_fail_before_any_work(data_dir, tmp_path, capsys, text, message):
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(text.replace('"."', f'"{data_dir / "middlebury_eval3_Q" / "Teddy"}"'))
    with pytest.raises(InputError, match="^" + str(sweep_file).replace(".", r"\.")):
        load_sweep(sweep_file)
    db = tmp_path / "results.sqlite"
    code = main(["sweep", str(sweep_file), "--db", str(db)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not db.exists()  # nothing started


@pytest.mark.parametrize("text", ["max_ratio = " + "{a = " * 5000 + "1" + "}" * 5000,
                                  "[" + ".".join(["a"] * 5000) + "]"], ids=["deep-inline-tables", "deep-header"])
def test_eval_config_nested_too_deep_is_refused_in_one_line(data_dir, tmp_path, capsys, text):
    """An audit: 'eval SCENE --config deep.toml' ended in "internal error: RecursionError", exit 1."""
    config = tmp_path / "deep.toml"
    config.write_text(text + "\n")
    assert main(["eval", str(data_dir / "middlebury_eval3_Q" / "Teddy"), "--config", str(config)]) == 2
    assert capsys.readouterr().err.strip() == (f"svs-depth eval: error: --config: {config}: tables or arrays nested "
                                               "too deep to be a configuration (over 32 levels)")


@pytest.mark.parametrize("name, message", [
    ("x" * 300 + ".toml", "--config: not a usable path (File name too long): "),
    ("/dev/null", "--config: /dev/null: expected a TOML file, got a special file")], ids=["too-long", "device"])
def test_eval_config_that_no_file_can_be_is_named_by_its_option(data_dir, tmp_path, capsys, name, message):
    """An audit: 'eval SCENE --config NAME' with a name over the file system's limit ended 'error: File name too
    long: NAME', exit 1, the option unnamed; /dev/null was 'expected a TOML file, got a folder'."""
    assert main(["eval", str(data_dir / "middlebury_eval3_Q" / "Teddy"), "--config", str(tmp_path / name)
                 if not name.startswith("/") else name]) == 2
    assert capsys.readouterr().err.strip().startswith("svs-depth eval: error: " + message)


@pytest.mark.parametrize("value", ["[" * 50_000 + "]" * 50_000, "{a = " * 5000 + "1" + "}" * 5000],
                         ids=["deep-array", "deep-inline-table"])
def test_eval_set_nested_too_deep_is_refused_in_one_line(data_dir, capsys, value):
    """An audit: 'eval SCENE --set seed=[[[[...]]]]' (50 000 deep) ended in "internal error: RecursionError"."""
    assert main(["eval", str(data_dir / "middlebury_eval3_Q" / "Teddy"), "--set", f"seed={value}"]) == 2
    assert capsys.readouterr().err.strip() == (
        "svs-depth eval: error: --set: seed: expected a setting's value, got one nested too deep")


def test_a_sweep_file_saved_by_a_windows_editor_is_read(data_dir, tmp_path):
    """A byte-order mark and CRLF line ends (Notepad's UTF-8): the mark made it "not valid TOML: Invalid statement
    (at line 1, column 1)", where a pair list saved so was read (its own "utf-8-sig")."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_bytes(b"\xef\xbb\xbf" + f'paths = ["{teddy}"]\r\n[grid]\r\n"max_ratio" = [0.6, 0.8]\r\n'.encode())
    assert len(load_sweep(sweep_file).configs) == 2


def test_a_sweep_files_relative_path_names_what_eval_opens_through_a_linked_folder(data_dir, tmp_path):
    """The paths of a sweep file reached through a linked folder (a checkout reached by a link, as ~/svs ->
    /work/main): "../lists/pairs.txt" is beside the link's target, as eval, ls and the system open it. The path
    was normalised by its letters first (link/.. taken as the link's own folder), and the sweep refused the file
    eval ran ("paths: no such file or folder"), or would have run another folder of that name; results --csv
    showed such a pair's path so normalised, a file that is not the pair's."""
    from svs_torch.evaluation import PairEvaluation
    from svs_torch.evaluation.report import csv_table
    from svs_torch.evaluation.store import ResultStore

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    for folder in ("exp", "lists", "scenes"):
        (tmp_path / "real" / folder).mkdir(parents=True)
    (tmp_path / "real" / "scenes" / "Teddy").symlink_to(teddy)
    (tmp_path / "real" / "lists" / "pairs.txt").write_text("../scenes/Teddy\n")
    (tmp_path / "real" / "exp" / "sweep.toml").write_text('paths = ["../lists/pairs.txt"]\n')
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "exp").symlink_to(tmp_path / "real" / "exp")
    sweep = load_sweep(tmp_path / "other" / "exp" / "sweep.toml")
    assert [os.path.realpath(source.left) for source in sweep.sources] == [os.path.realpath(teddy)]
    with ResultStore(tmp_path / "runs.sqlite") as store:
        store.add_pairs(sweep.sources)
        store.add_configs([c.record() for c in sweep.configs])
        row = PairEvaluation("Teddy", "OK", acc_r_min_pct=99.0)
        store.write_task(sweep.configs[0].config_id, store.start_run("test", "v", {}, ""),
                         [(sweep.sources[0].pair_id, row)])
        header, rows = csv_table(store)
    assert os.path.realpath(rows[0][header.index("left")]) == os.path.realpath(teddy)
    # Where the letters and the system agree, the path is still shown without its inner "..".
    plain = load_sweep(tmp_path / "real" / "exp" / "sweep.toml")
    assert [source.list_file for source in plain.sources] == [str(tmp_path / "real" / "lists" / "pairs.txt")]


def test_plan_skips_blocks_that_are_stored(data_dir, tmp_path):
    sweep = load_sweep(write_sweep(tmp_path, data_dir, SWEEP.replace("batch_size = 1", "batch_size = 3")))
    assert [len(t.sources) for t in plan_tasks(sweep, set())] == [3, 1] * 3
    first = sweep.configs[0].config_id
    done = {(first, s.pair_id) for s in sweep.sources[:3]} | {(first, sweep.sources[3].pair_id)}
    tasks = plan_tasks(sweep, done | {(sweep.configs[1].config_id, sweep.sources[0].pair_id)})
    # Config 0 is complete; config 1 lacks three pairs, run as one block without its stored first pair (left alone
    # twice, then fixed: a partly stored block ran whole, its stored pairs again).
    assert [(t.config_id, [s.pair_id for s in t.sources]) for t in tasks] == [
        (sweep.configs[1].config_id, [s.pair_id for s in sweep.sources[1:]]),
        (sweep.configs[2].config_id, [s.pair_id for s in sweep.sources[:3]]),
        (sweep.configs[2].config_id, [sweep.sources[3].pair_id])]


def _children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (from /proc)."""
    children = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                children.append(int(entry.name))
    return children


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the worker processes")
def test_sweep_killed_with_sigkill_resumes_to_the_uninterrupted_rows(reference, tmp_path, capsys):
    sweep_file, reference_db = reference
    db = tmp_path / "killed.sqlite"
    command = [sys.executable, "-m", "svs_torch.cli", "sweep", str(sweep_file), "--db", str(db)]
    process = subprocess.Popen(command + ["--workers", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while count_rows(db) < 2 and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        workers = _children(process.pid)
        os.kill(process.pid, signal.SIGKILL)  # the sweep itself, mid-run: no handler, no clean-up
        process.wait()
        before = count_rows(db)
        assert 2 <= before < TOTAL_ROWS, f"not killed mid-run: {before} rows"
        gone = time.monotonic() + 10
        while any(_alive(pid) for pid in workers) and time.monotonic() < gone:
            time.sleep(0.1)
        assert not any(_alive(pid) for pid in workers), "a worker outlived its killed sweep"
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert sqlite3.connect(db).execute("PRAGMA integrity_check").fetchone() == ("ok",)
    # Resumed in this process (only the kill needs a process of its own): the same command, without torch's import.
    code = main(command[3:] + ["--workers", "0", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    report = json.loads(out.strip().splitlines()[-1])
    # Only the missing rows ran; every row is there once; the values equal the uninterrupted run's.
    assert report["rows_written"] == TOTAL_ROWS - before and report["rows_stored"] == TOTAL_ROWS
    assert f"{before} rows already in" in err
    rows = stored_rows(db)
    assert len(rows) == TOTAL_ROWS == count_rows(db)
    assert rows == stored_rows(reference_db)
    assert {r["status"] for r in rows.values()} == {"OK"}


def test_dask_cluster_gives_the_rows_of_the_local_pool(reference, tmp_path):
    distributed = pytest.importorskip("distributed", reason="Dask distributed is not installed: "
                                                            "pip install -e '.[dask]' runs this test")
    import dask

    sweep_file, reference_db = reference
    warnings: list[str] = []
    # As experiments/dask_workers.yaml does for real workers: no MALLOC_TRIM_THRESHOLD_ from the nanny.
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        with distributed.LocalCluster(host="127.0.0.1", n_workers=1, threads_per_worker=1, processes=True,
                                      dashboard_address=":0") as cluster:
            assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
            db = tmp_path / "dask.sqlite"
            outcome = run_sweep(load_sweep(sweep_file), db, scheduler=cluster.scheduler_address,
                                warn=warnings.append)
    assert outcome.rows_written == TOTAL_ROWS and warnings == []
    assert stored_rows(db) == stored_rows(reference_db)
    environment = json.loads(sqlite3.connect(db).execute("SELECT environment FROM runs").fetchone()[0])
    assert environment["executor"] == "dask" and environment["threads_per_worker"] == 1


@pytest.mark.parametrize("omp, expected", [("1", (1, 1)), ("", (2, 1)), ("8", (2, 1))])
def test_a_sweep_keeps_to_omp_num_threads(data_dir, tmp_path, monkeypatch, omp, expected):
    """Found by an audit of the command line: `sweep` took every core whatever OMP_NUM_THREADS said (`estimate
    --pairs` honours it), so a job limited to one thread ran two workers, or one of two threads."""
    from svs_torch.evaluation import sweep as sweep_module

    pools = []

    def in_this_process(function, items, workers, threads):  # the pool's arguments; its tasks run here
        pools.append((workers, threads))
        return map(function, items)

    monkeypatch.setattr(sweep_module, "map_process_pool", in_this_process)
    monkeypatch.setattr(sweep_module, "available_cores", lambda: 2)
    monkeypatch.setattr("svs_torch.core.workers.available_cores", lambda: 2)
    monkeypatch.setenv("OMP_NUM_THREADS", omp)
    # One scene's three tasks, more than the two cores: the pool's arguments are what is checked (the reference's
    # twelve tasks, run here in turn, cost a second a case).
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(SWEEP.format(paths=f'"{data_dir / "middlebury_eval3_Q" / SCENES[0]}"'))
    threads = torch.get_num_threads()
    try:
        outcome = run_sweep(load_sweep(sweep_file), tmp_path / "limited.sqlite", warn=pytest.fail)
    finally:  # the tasks ran here (run_task gives the threads back; kept should it not)
        torch.set_num_threads(threads)
    assert pools == [expected] and outcome.rows_written == 3
    environment = json.loads(sqlite3.connect(tmp_path / "limited.sqlite").execute(
        "SELECT environment FROM runs").fetchone()[0])
    assert (environment["workers"], environment["threads_per_worker"]) == expected


def test_results_summary_csv_and_plot(reference, tmp_path, capsys):
    _, db = reference
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    assert "3 configurations" in out and "best by each metric:" in out and "segmentation.kernel_size=5" in out
    csv_path, figure = tmp_path / "rows.csv", tmp_path / "sweep.png"
    assert main(["results", str(db), "--csv", str(csv_path), "--plot", str(figure)]) == 0
    lines = csv_path.read_text().splitlines()
    assert len(lines) == 1 + TOTAL_ROWS
    assert lines[0].startswith("config,left,right,status,r_min_m,r_max_m,acc_r_min_pct,acc_r_max_pct,label,size,"
                               "param:segmentation.kernel_size,")
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["results", str(db), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert len(summary["configs"]) == 3 and all(c["pairs"] == 4 for c in summary["configs"])
    assert main(["results", str(tmp_path / "none.sqlite")]) == 2
    assert "expected a results file" in capsys.readouterr().err
    for both in ("--json", "--summary"):  # was: the JSON summary the CSV's last line, or the summary dropped
        assert main(["results", str(db), "--csv", both]) == 2
        assert f"--csv: the table and {both} would both go to standard output" in capsys.readouterr().err


def test_sweeps_refuse_another_programs_file_that_has_a_meta_table(data_dir, tmp_path, capsys):
    """Found by an audit: a file of another program's with a table named meta (a common name) beside its own was
    taken for a store: eval --db and sweep added the store's tables to it (and, where its meta had other columns,
    failed only after, "no such column: value"). Each is refused now, the file left as it was; a store made by a
    sweep, and one whose meta lost its row, are still written."""
    import hashlib

    teddy = str(data_dir / "middlebury_eval3_Q" / "Teddy")
    files = {"users": "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT); CREATE TABLE users (id INTEGER)",
             "columns": "CREATE TABLE meta (name TEXT, v INTEGER)",
             "keys": "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT); INSERT INTO meta VALUES ('owner', 'x')"}
    for name, script in files.items():
        path = tmp_path / f"{name}.sqlite"
        with contextlib.closing(sqlite3.connect(path)) as connection:
            connection.executescript(script)
        before = hashlib.sha256(path.read_bytes()).hexdigest()
        assert main(["eval", teddy, "--size", "160x120", "--db", str(path)]) == 2, name
        assert "is another program's SQLite file (" in capsys.readouterr().err, name
        assert hashlib.sha256(path.read_bytes()).hexdigest() == before, name
    store = tmp_path / "store.sqlite"
    assert main(["eval", teddy, "--size", "160x120", "--db", str(store)]) == 0
    with contextlib.closing(sqlite3.connect(store)) as connection, connection:
        connection.execute("DELETE FROM meta")
    assert main(["eval", teddy, "--size", "160x120", "--db", str(store)]) == 0
    capsys.readouterr()


def test_results_leave_other_files_alone_and_sweeps_refuse_them(reference, data_dir, tmp_path, capsys):
    """Found by an audit of the results store: `results` (a read) turned another program's SQLite file into WAL
    mode and a 0-byte file into a 4 KB one while refusing them, and `sweep` / `eval --db` added the store's tables
    beside another program's own."""
    import hashlib

    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as connection:
        connection.execute("CREATE TABLE t (x)")
    empty = tmp_path / "empty.sqlite"
    empty.touch()
    before = {path: hashlib.sha256(path.read_bytes()).hexdigest() for path in (other, empty)}
    for path in (other, empty):
        assert main(["results", str(path)]) == 2
        assert "is not a results store" in capsys.readouterr().err
    assert before == {path: hashlib.sha256(path.read_bytes()).hexdigest() for path in (other, empty)}
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    assert main(["eval", str(teddy), "--size", "160x120", "--db", str(other)]) == 2
    assert "is another program's SQLite file (tables t), not a results store" in capsys.readouterr().err
    assert before[other] == hashlib.sha256(other.read_bytes()).hexdigest()


def test_results_read_a_store_in_a_folder_they_cannot_write(reference, monkeypatch, capsys,
                                                            store_folder_not_writable):
    """Found by an audit of the results store: a WAL store needs its folder writable even to be read (its
    shared-memory file), so a colleague's store on a read-only share was "not a results store (unable to open
    database file)". A store closed cleanly is then read as an immutable file (the refusal is simulated: root
    writes anywhere)."""
    _, db = reference
    store_folder_not_writable()
    assert main(["results", str(db), "--json"]) == 0
    assert len(json.loads(capsys.readouterr().out)["configs"]) == 3
    monkeypatch.undo()
    assert not Path(f"{db}-wal").exists() and not Path(f"{db}-shm").exists()  # nothing left beside it


def test_native_size_rows_do_not_depend_on_the_batch_size(data_dir, tmp_path):
    """Scenes of four native sizes padded into one task's batch (issue 29: 99.0 % at batch_size = 1 and 86.4 % at 4
    under the same configuration ids): the same ids and the same rows at either batch size."""
    native = SWEEP.replace('size = "160x120"', 'size = "native"').replace("[3, 5, 7]", "[3, 5]")
    one = run_sweep(load_sweep(write_sweep(tmp_path, data_dir, native)), tmp_path / "one.sqlite", workers=0)
    four = run_sweep(load_sweep(write_sweep(tmp_path, data_dir, native.replace("batch_size = 1", "batch_size = 4"))),
                     tmp_path / "four.sqlite", workers=0)
    assert (one.rows_written, four.rows_written, four.tasks) == (8, 8, 2)
    assert stored_rows(tmp_path / "one.sqlite") == stored_rows(tmp_path / "four.sqlite")


def test_weights_content_is_part_of_the_configuration_id(tmp_path):
    """A learned segmenter's weights retrained in place are another configuration, not the same id."""
    from svs_torch.evaluation.sweep import make_sweep_config
    from svs_torch.segmentation.network_files import SHIPPED_WEIGHTS

    weights = tmp_path / "net.pt"
    shutil.copyfile(SHIPPED_WEIGHTS, weights)
    overrides = {"segmentation.segmenter": f"learned:{weights}"}
    before = make_sweep_config("default", overrides, (320, 240)).config_id
    assert make_sweep_config("default", overrides, (320, 240)).config_id == before
    weights.write_bytes(weights.read_bytes() + b"\0")
    assert make_sweep_config("default", overrides, (320, 240)).config_id != before
    assert make_sweep_config("default", {}, (320, 240)).config_id != before


def test_rows_of_several_code_versions_are_never_mixed_silently(reference, tmp_path, capsys):
    db = tmp_path / "mixed.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("INSERT INTO runs(started_unix_s, command, code_version, environment, sweep) "
                           "VALUES (0, 'sweep', '0.0.1+git.old', '{}', '')")
        old_run = connection.execute("SELECT max(run_id) FROM runs").fetchone()[0]
        connection.execute("UPDATE results SET run_id = ? WHERE rowid IN (SELECT rowid FROM results LIMIT 2)",
                           (old_run,))
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    assert "rows come from 2 code versions" in out and "0.0.1+git.old" in out
    csv_path = tmp_path / "rows.csv"
    assert main(["results", str(db), "--csv", str(csv_path)]) == 0
    header, *rows = csv_path.read_text().splitlines()
    assert header.endswith(",code_version") and sum(r.endswith(",0.0.1+git.old") for r in rows) == 2
    assert main(["results", str(reference[1])]) == 0
    assert "code versions" not in capsys.readouterr().out


def test_a_resumed_sweep_says_when_the_rows_it_keeps_are_of_another_code_version(reference, tmp_path):
    """Found by an audit: a sweep run again after a code change said "N rows already in DB, 0 to run" and no more,
    its whole table the old code's; now a warning counts the rows kept from other versions and names them."""
    db = tmp_path / "old_code.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("UPDATE runs SET code_version = '0.0.1+git.old'")
    messages: list[str] = []
    outcome = run_sweep(load_sweep(reference[0]), db, workers=0, warn=messages.append)
    assert outcome.tasks == 0
    assert [m for m in messages if f"{TOTAL_ROWS} of the {TOTAL_ROWS} rows this sweep keeps" in m
            and "other code versions (0.0.1+git.old) and are not run again" in m], messages
    messages.clear()
    run_sweep(load_sweep(reference[0]), tmp_path / "copy.sqlite", workers=0, warn=messages.append)
    run_sweep(load_sweep(reference[0]), tmp_path / "copy.sqlite", workers=0, warn=messages.append)
    assert not [m for m in messages if "code version" in m], messages  # one version: nothing to say


def test_a_resumed_sweep_says_when_the_files_of_rows_it_keeps_changed_since(data_dir, tmp_path, capsys):
    """Found by an audit: a scene's image overwritten in place (with another scene's) and the sweep run again said
    "2 rows already in DB, 0 to run", its row the old image's, and results read it without a word; now a warning
    and a note count the rows whose files changed after they were stored, and name the pair."""
    for name in ("Teddy", "ArtL"):
        shutil.copytree(data_dir / "middlebury_eval3_Q" / name, tmp_path / name)
    sweep_file = tmp_path / "changed.toml"
    sweep_file.write_text(f'paths = ["{tmp_path / "Teddy"}", "{tmp_path / "ArtL"}"]\nsize = "160x120"\n')
    db, messages = tmp_path / "changed.sqlite", []
    assert run_sweep(load_sweep(sweep_file), db, workers=0, warn=pytest.fail).rows_written == 2
    run_sweep(load_sweep(sweep_file), db, workers=0, warn=pytest.fail)  # nothing changed: nothing to say
    image = tmp_path / "Teddy" / "im1.png"
    image.write_bytes(image.read_bytes())  # rewritten in place: the folder's own time stays
    os.utime(image, (time.time() + 5, time.time() + 5))  # past any run's start, whatever the clock's grain
    outcome = run_sweep(load_sweep(sweep_file), db, workers=0, warn=messages.append)
    assert outcome.tasks == 0
    assert [m for m in messages if "1 of the 2 rows this sweep keeps" in m and "files changed since" in m
            and "/Teddy) and are not run again" in m], messages
    capsys.readouterr()
    assert main(["results", str(db)]) == 0  # and the table, read after an eval --db kept the old row, says so
    assert f"note: 1 of the 2 rows in {db} are of pairs whose files changed since the row was stored (" in (
        capsys.readouterr().out)


def test_results_say_when_configurations_were_measured_by_different_code_versions(reference, tmp_path, capsys):
    """Found by an audit: a sweep resumed after a code change (its new configurations run by the new code, the
    stored ones kept from the old) ranked them side by side without a word, each configuration of one version."""
    db = tmp_path / "two_versions.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("INSERT INTO runs(started_unix_s, command, code_version, environment, sweep) "
                           "VALUES (0, 'sweep', '0.0.1+git.old', '{}', '')")
        old_run = connection.execute("SELECT max(run_id) FROM runs").fetchone()[0]
        old_config = connection.execute("SELECT min(config_id) FROM results").fetchone()[0]
        connection.execute("UPDATE results SET run_id = ? WHERE config_id = ?", (old_run, old_config))
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    assert "rows come from" not in out  # no configuration mixes versions ...
    assert "measured by 2 code versions (" in out and f"0.0.1+git.old: {old_config}" in out  # ... the store does


def test_results_say_when_configurations_were_measured_on_different_pairs(reference, tmp_path, capsys):
    """Found by a review of the evaluation: after an interrupted sweep each configuration was summarised over the
    rows it had, and ranked against the others over different pairs without a word."""
    db = tmp_path / "interrupted.sqlite"
    with edited_copy(reference, db) as connection:
        config_id = connection.execute("SELECT config_id FROM results ORDER BY config_id LIMIT 1").fetchone()[0]
        connection.execute("DELETE FROM results WHERE rowid IN (SELECT rowid FROM results WHERE config_id = ? "
                           "LIMIT 2)", (config_id,))
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    assert f"not all measured on the same pairs ({config_id} lacks 2)" in out
    assert main(["results", str(reference[1])]) == 0
    assert "same pairs" not in capsys.readouterr().out


def test_results_say_the_configurations_a_stopped_sweep_never_ran(reference, tmp_path, capsys):
    """Found by an audit of the bulk commands: a sweep stopped after 40 of its 1000 configurations read as a finished
    one ("40 configurations", the best of them), since each configuration had all its pairs or none: the note of
    pairs missing never fired. Now the configurations recorded without a row are counted, said and in JSON."""
    db = tmp_path / "stopped.sqlite"
    with edited_copy(reference, db) as connection:
        config_id = connection.execute("SELECT config_id FROM results ORDER BY config_id LIMIT 1").fetchone()[0]
        connection.execute("DELETE FROM results WHERE config_id = ?", (config_id,))
        recorded = connection.execute("SELECT count(*) FROM configs").fetchone()[0]
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith(f"{recorded - 1} configurations; ranked by")
    assert out.splitlines()[1] == (f"note: 1 more configuration recorded in {db} has no row yet (not run yet by a run "
                                   f"still going, or a run stopped before it): the ranking and the best are of the "
                                   f"{recorded - 1} run so far; the run going on, or the same command run again, fills "
                                   "the rest")
    assert main(["results", str(db), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["configs_without_rows"] == 1
    assert main(["results", str(reference[1]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["configs_without_rows"] == 0
    assert main(["results", str(reference[1])]) == 0
    assert "no row yet" not in capsys.readouterr().out


def test_results_say_the_pairs_a_stopped_run_never_reached(data_dir, reference, tmp_path, capsys):
    """Found by an audit: an eval --db (or a sweep of one configuration) stopped after 8 of its 45 pairs read as a
    finished table, "8 pairs" and their means, since no other configuration had the 37 others. The pairs recorded
    without a row in any configuration are counted now, said and in JSON."""
    db = tmp_path / "stopped.sqlite"
    with edited_copy(reference, db) as connection:
        pair_id = connection.execute("SELECT pair_id FROM results ORDER BY pair_id LIMIT 1").fetchone()[0]
        connection.execute("DELETE FROM results WHERE pair_id = ?", (pair_id,))
    assert main(["results", str(db)]) == 0
    assert (f"note: 1 more pair recorded in {db} has no row in any configuration yet (not run yet by a run still "
            "going, or a run stopped before it)") in capsys.readouterr().out
    assert main(["results", str(db), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["pairs_without_rows"] == 1
    assert main(["results", str(reference[1]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["pairs_without_rows"] == 0
    bad_lines = tmp_path / "bad_lines.txt"  # rows of lines that could not be read: each pair has its row
    bad_lines.write_text(f"{data_dir / 'middlebury_eval3_Q' / 'Teddy'}\nnone/left.png none/right.png\n1 2 3\n")
    assert main(["eval", str(bad_lines), "--size", "160x120", "--db", str(tmp_path / "bad.sqlite")]) == 0
    capsys.readouterr()
    assert main(["results", str(tmp_path / "bad.sqlite"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["pairs_without_rows"] == 0


@pytest.mark.skipif(not (os.name == "posix" and hasattr(__import__("fcntl"), "F_OFD_SETLK")),
                    reason="needs open-file-description locks (Linux)")
def test_results_say_the_pairs_a_running_sweep_has_not_reached_yet_are_not_run_yet(reference, tmp_path, capsys):
    """From the lead's brief: results on a store a run was still writing said of the pairs it had not reached yet
    "never run: a run stopped before them" (--json's help; the table's note: "stopped before it?"). A sweep holds
    its claims while it runs, which results reads: the notes then say the pairs are not run yet and --json says
    writing (an eval --db holds its configuration too, test_evaluation.py); where none holds any, the note says both
    what may be."""
    from svs_torch.evaluation.store import ResultStore

    db = tmp_path / "running.sqlite"
    with edited_copy(reference, db) as connection:
        pair_id = connection.execute("SELECT pair_id FROM results ORDER BY pair_id LIMIT 1").fetchone()[0]
        connection.execute("DELETE FROM results WHERE pair_id = ?", (pair_id,))
    empty = tmp_path / "empty.sqlite"  # (the sweep has not stored its first row yet)
    with edited_copy(reference, empty) as connection:
        connection.execute("DELETE FROM results")
    with ResultStore(db) as running, ResultStore(empty) as starting:
        running.claim_for_a_sweep(["a configuration of the running sweep"])
        starting.claim_for_a_sweep(["a configuration of the running sweep"])
        assert main(["results", str(empty)]) == 0
        assert capsys.readouterr().out.endswith("no pair run); the run writing it now fills it\n")
        assert main(["results", str(db)]) == 0
        out = capsys.readouterr().out
        assert (f"note: 1 more pair recorded in {db} has no row in any configuration yet (not run yet: a sweep or "
                "an eval --db is writing the store now): the means are over the pairs run so far; the run writing it "
                "fills those it covers" in out), out
        assert "stopped" not in out
        assert main(["results", str(db), "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["writing"] is True
    assert main(["results", str(db), "--json"]) == 0
    saved = json.loads(capsys.readouterr().out)
    assert saved["writing"] is False and saved["pairs_without_rows"] == 1
    assert main(["results", str(db)]) == 0
    assert "(not run yet by a run still going, or a run stopped before it)" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["results", "--help"])
    assert "never run" not in capsys.readouterr().out


def test_results_of_an_eval_store_without_rows_does_not_send_the_user_to_a_sweep(tmp_path, capsys):
    """Found reviewing bbf0f95 (results' notes of a store a run is still writing): a store with no row yet and no
    sweep writing it still said "running the sweep's command again fills it", where an eval --db, which records its
    configuration and pairs before its first row and then held no claim, had made it (read while it ran, or after it
    stopped). It now says what the notes of a store with rows say."""
    from svs_torch.evaluation.store import ResultStore
    from svs_torch.evaluation.sweep import make_sweep_config

    db = tmp_path / "eval.sqlite"
    with ResultStore(db) as store:  # as eval --db leaves it before its first row (cli/eval_store.py's _open_store)
        store.add_configs([make_sweep_config("default", {}, None).record()])
        store.start_run("eval", "abc1234", {}, "eval pairs.txt --db eval.sqlite")
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    assert out == (f"{db}: no results yet (1 configuration recorded, no pair run); the run going on, or the same "
                   "command run again, fills it\n"), out


@pytest.mark.skipif(not (os.name == "posix" and hasattr(__import__("fcntl"), "F_OFD_SETLK")),
                    reason="needs open-file-description locks (Linux)")
def test_the_figure_of_a_store_a_sweep_is_writing_does_not_say_a_sweep_stopped(reference, tmp_path):
    """Found reviewing bbf0f95 (results' notes of a store a run is still writing): results --figure on a store a
    sweep was writing titled the figure "each mean is over the rows stored (a sweep stopped before the rest? ...)",
    while the table of the same command said the sweep was writing it. The title now says what the notes say."""
    import svs_torch.evaluation.report as report
    from svs_torch.evaluation.store import ResultStore

    db = tmp_path / "running.sqlite"
    with edited_copy(reference, db) as connection:
        last = connection.execute("SELECT max(config_id) FROM results").fetchone()[0]
        connection.execute("DELETE FROM results WHERE config_id = ?", (last,))
    titles = []
    real = report.results_figure
    with pytest.MonkeyPatch.context() as patch:  # the title of each figure written
        patch.setattr(report, "results_figure", lambda *args: (figure := real(*args), titles.append(
            figure.get_suptitle()))[0])
        with ResultStore(db) as running:
            running.claim_for_a_sweep(["a configuration of the running sweep"])
            assert main(["results", str(db), "--figure", str(tmp_path / "running.png")]) == 0
        assert main(["results", str(db), "--figure", str(tmp_path / "stopped.png")]) == 0
    writing, after = (" ".join(title.split()) for title in titles)
    assert "stopped" not in writing and "(a sweep or an eval --db is writing the store now)" in writing, writing
    assert "(a run still going, or one stopped before the rest: the same command run again fills it)" in after, after


def test_csv_parameter_columns_hold_the_values_that_ran(data_dir, tmp_path, capsys):
    """Found by a review of the evaluation: a param: column held the override, so a configuration that kept its
    preset's value showed an empty cell (the default's max_ratio 0.8, the paper preset's 0.6)."""
    import csv
    import io

    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(f'paths = ["{data_dir / "middlebury_eval3_Q" / "Teddy"}"]\nsize = "160x120"\n'
                          '[[configs]]\n[[configs]]\nmax_ratio = 0.7\n[[configs]]\npreset = "paper"\n')
    store = tmp_path / "s.sqlite"
    assert main(["sweep", str(sweep_file), "--db", str(store), "--workers", "0"]) == 0
    capsys.readouterr()
    assert main(["results", str(store), "--csv", "-"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    ran = {(row["param:preset"], row["label"]): float(row["param:max_ratio"]) for row in rows}
    assert ran == {("default", "(preset)"): PipelineConfig().max_ratio, ("default", "max_ratio=0.7"): 0.7,
                   ("paper", "preset=paper"): PipelineConfig.paper().max_ratio}
    # The figure's panels too (found by an audit: its max_ratio panel had a level "None" averaging the default's
    # 0.8 and the paper preset's 0.6); and a store of two sizes gets a size panel (its rows were averaged in silence).
    from svs_torch.evaluation.report import results_figure
    from svs_torch.evaluation.store import ResultStore

    sweep_file.write_text(f'paths = ["{data_dir / "middlebury_eval3_Q" / "Teddy"}"]\nsize = "128x96"\n')
    assert main(["sweep", str(sweep_file), "--db", str(store), "--workers", "0"]) == 0
    with ResultStore(store, create=False) as opened:
        figure = results_figure(opened)
    panels = {axis.get_xlabel(): [tick.get_text() for tick in axis.get_xticklabels()] for axis in figure.axes}
    assert panels["max_ratio"] == ["0.6", "0.7", "0.8"]
    assert sorted(panels["size"]) == ["128x96", "160x120"] and panels["preset"] == ["paper", "default"]


def test_rows_stored_counts_this_sweeps_rows_only(data_dir, tmp_path, capsys):
    """Found by an audit of sweep: a store holding the same configuration on other pairs gave "3 of 1 stored" and
    rows_stored 3 for a sweep of one pair (the store's rows of that configuration were counted, not the sweep's)."""
    teddy, artl = (data_dir / "middlebury_eval3_Q" / name for name in ("Teddy", "ArtL"))
    both, one = tmp_path / "both.toml", tmp_path / "one.toml"
    both.write_text(f'paths = ["{teddy}", "{artl}"]\nsize = "128x96"\n')
    one.write_text(f'paths = ["{teddy}"]\nsize = "128x96"\n')
    store = tmp_path / "s.sqlite"
    assert main(["sweep", str(both), "--db", str(store), "--workers", "0", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["rows_stored"] == 2
    assert main(["sweep", str(one), "--db", str(store), "--workers", "0", "--json"]) == 0
    out, err = capsys.readouterr()
    summary = json.loads(out.splitlines()[-1])
    assert (summary["rows_stored"], summary["rows_total"], summary["rows_written"]) == (1, 1, 0)
    assert "1 row already in" in err and "1 of 1 stored" in err
    assert "svs-depth sweep: 1 configuration x 1 pair; " in err  # not "1 configurations x 1 pairs"


def test_a_sweeps_progress_counts_rows_not_pairs(data_dir, tmp_path, capsys):
    """Found by an audit of the results' numbers: a sweep of 2 configurations over 10 pairs said 'sweep: 20/20
    pairs', its items being (configuration, pair) rows, as its first line counts them."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    sweep_file = tmp_path / "two.toml"
    sweep_file.write_text(f'paths = ["{teddy}"]\nsize = "128x96"\n[grid]\n"segmentation.kernel_size" = [3, 5]\n')
    assert main(["sweep", str(sweep_file), "--db", str(tmp_path / "s.sqlite"), "--workers", "0"]) == 0
    err = capsys.readouterr().err
    assert "svs-depth sweep: 2 configurations x 1 pair; 0 rows already in" in err and "2 to run" in err
    assert "sweep: 2/2 rows in " in err and "/2 pairs" not in err


def test_a_sweeps_count_says_the_failed_rows_it_stored(data_dir, tmp_path, capsys):
    """Found by an audit: a list with a pair whose right image is missing ended "2 of 4 stored" (and rows_stored 2)
    while the file held 4 rows, 2 of them BAD_INPUT, which a resume runs again; the line now says so."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{teddy / 'im0.png'} {teddy / 'im1.png'}\n{teddy / 'im0.png'} {tmp_path / 'gone.png'}\n")
    sweep = tmp_path / "bad.toml"
    sweep.write_text(f'paths = ["{pairs}"]\nsize = "128x96"\n[grid]\nseed = [0, 1]\n')
    store = tmp_path / "s.sqlite"
    assert main(["sweep", str(sweep), "--db", str(store), "--workers", "0", "--json"]) == 0
    out, err = capsys.readouterr()
    summary = json.loads(out.splitlines()[-1])
    assert (summary["rows_stored"], summary["rows_to_retry"], summary["rows_total"]) == (2, 2, 4)
    assert "2 of 4 stored in" in err and "(2 more failed there: BAD_INPUT, TOO_SMALL or ERROR rows" in err


def test_a_scheduler_that_cannot_be_reached_leaves_no_store(data_dir, tmp_path, monkeypatch, capsys):
    """Found by an audit of sweep: --scheduler at an address with no scheduler (or no workers) failed after the
    store was made with its configurations and no row, which `results` then listed as "0 configurations"."""
    import svs_torch.evaluation.sweep as sweep_module

    def unreachable(address, warn):
        raise InputError(f"--scheduler: cannot reach a Dask scheduler at {address!r} (timed out)")

    monkeypatch.setattr(sweep_module, "connect_dask", unreachable)
    sweep_file = tmp_path / "one.toml"
    sweep_file.write_text(f'paths = ["{data_dir / "middlebury_eval3_Q" / "Teddy"}"]\nsize = "128x96"\n')
    store = tmp_path / "s.sqlite"
    assert main(["sweep", str(sweep_file), "--db", str(store), "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "cannot reach a Dask scheduler" in capsys.readouterr().err and not store.exists()


def test_a_capture_folder_kept_with_its_rig_calibration_is_refused_not_ranged_in_the_svs_model(data_dir, tmp_path,
                                                                                                   capsys):
    """Found by an audit of sweep: a capture folder's index.jsonl with the calibration.json that capture
    --calibration keeps beside it was swept unrectified in the SVS model's metres and stored without a word, where
    eval and estimate --pairs rectify its pairs with that copy (and eval --db refuses it)."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    captured = tmp_path / "walk"
    captured.mkdir()
    (captured / "index.jsonl").write_text(json.dumps({"left": str(teddy / "im0.png"),
                                                      "right": str(teddy / "im1.png")}) + "\n")
    sweep_file = tmp_path / "one.toml"
    sweep_file.write_text('paths = ["walk/index.jsonl"]\nsize = "128x96"\n')
    store = tmp_path / "s.sqlite"
    (captured / "calibration.json").write_text("{}")
    assert main(["sweep", str(sweep_file), "--db", str(store), "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{sweep_file}: paths: {captured / 'index.jsonl'} was captured with a rig calibration" \
        in err[0] and not store.exists(), err
    (captured / "calibration.json").unlink()  # a folder captured without one is swept as before
    assert main(["sweep", str(sweep_file), "--db", str(store), "--workers", "0"]) == 0


def test_a_capture_folder_whose_kept_rig_calibration_is_gone_is_refused(data_dir, tmp_path, capsys):
    """Found by an audit of recordings: a capture --calibration folder copied without its calibration.json was swept
    in the SVS model's metres as one captured without a rig; its index lines now name the copy (rig_calibration,
    guide --record's calibration_rectified), and such a folder is refused as one with the copy is."""
    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    captured = tmp_path / "walk"
    captured.mkdir()
    for key, value in (("rig_calibration", "calibration.json"), ("calibration_rectified", True)):
        (captured / "index.jsonl").write_text(json.dumps({"left": str(teddy / "im0.png"),
                                                          "right": str(teddy / "im1.png"), key: value}) + "\n")
        sweep_file = tmp_path / "one.toml"
        sweep_file.write_text('paths = ["walk/index.jsonl"]\nsize = "128x96"\n')
        store = tmp_path / "s.sqlite"
        assert main(["sweep", str(sweep_file), "--db", str(store), "--workers", "0"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{sweep_file}: paths: {captured / 'index.jsonl'} lists pairs captured with a rig " \
            "calibration, which is no longer beside it" in err[0] and not store.exists(), err


def test_one_configuration_reached_by_two_descriptions_keeps_both_labels(tmp_path):
    """Found by an audit: a configuration stored by one sweep and reached again by another under another description
    (``max_ratio=0.8`` is the default's value) was summarised under the first sweep's label alone, so the second
    sweep's rows appeared as ``(preset)``; within one sweep the last description won."""
    from svs_torch.evaluation.store import ResultStore
    from svs_torch.evaluation.sweep import make_sweep, make_sweep_config

    default = make_sweep_config("default", {}, None, "(preset)")
    same = make_sweep_config("default", {"max_ratio": PipelineConfig().max_ratio}, None, "max_ratio=0.8")
    other = make_sweep_config("default", {"max_ratio": 0.7}, None, "max_ratio=0.7")
    assert same.config_id == default.config_id != other.config_id
    sweep = make_sweep([], [default, other, same], None)
    assert [c.label for c in sweep.configs] == ["(preset) | max_ratio=0.8", "max_ratio=0.7"]
    with ResultStore(tmp_path / "runs.sqlite") as store:
        store.add_configs([default.record()])
        store.add_configs([same.record(), other.record()])
        store.add_configs([same.record(), default.record()])  # a sweep run again: no label twice
        labels = {c["config_id"]: c["label"] for c in store.configs()}
    assert labels == {default.config_id: "(preset) | max_ratio=0.8", other.config_id: "max_ratio=0.7"}


def test_a_sweep_file_listing_one_configuration_twice_says_so(data_dir, tmp_path):
    """Found by an audit of sweeps: a grid holding the same value twice, or a [[configs]] entry setting what the
    preset already has, made fewer configurations than the file lists (each runs once) and the sweep said only "2
    configurations", never why; now a warning counts them and names a repeat."""
    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    path = tmp_path / "twice.toml"
    path.write_text(f'paths = ["{scene}"]\nsize = "160x120"\n[grid]\n"segmentation.kernel_size" = [5, 5, 3]\n')
    with pytest.warns(UserWarning, match=r"twice.toml: 3 configurations listed, 2 distinct: 1 repeats one listed "
                                         r"before \('segmentation.kernel_size=5' twice\); each runs once"):
        assert len(load_sweep(path).configs) == 2
    ratio = PipelineConfig().max_ratio
    path.write_text(f'paths = ["{scene}"]\nsize = "160x120"\n[[configs]]\n[[configs]]\nmax_ratio = {ratio}\n')
    with pytest.warns(UserWarning, match=rf"2 configurations listed, 1 distinct: 1 repeats one listed before "
                                         rf"\('max_ratio={ratio}' is '\(preset\)'\)"):
        assert [c.label for c in load_sweep(path).configs] == [f"(preset) | max_ratio={ratio}"]
    path.write_text(f'paths = ["{scene}"]\nsize = "160x120"\n[grid]\n"segmentation.kernel_size" = [3, 5]\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # distinct configurations: no word
        assert len(load_sweep(path).configs) == 2


def test_configurations_of_two_sweeps_differing_only_in_set_are_told_apart(data_dir, tmp_path, capsys):
    """Left alone twice, then fixed: two sweep files into one store that differ only in their fixed ``[set]`` values
    labelled their configurations by the grid alone, so `results` listed "segmentation.kernel_size=3" twice with
    different numbers (and the CSV's label column, and the figure's title, could not tell them apart)."""
    from svs_torch.data import PairSource
    from svs_torch.evaluation import PairEvaluation
    from svs_torch.evaluation.report import config_summaries, csv_table, distinct_labels
    from svs_torch.evaluation.store import ResultStore

    scene = data_dir / "middlebury_eval3_Q" / "Teddy"
    text = (f'paths = ["{scene}"]\nsize = "128x96"\n[set]\nmax_ratio = {{}}\n'
            '[grid]\n"segmentation.kernel_size" = [3, 5]\n')
    sweeps = []
    for name, ratio in (("a", 0.7), ("b", 0.9)):
        (tmp_path / f"{name}.toml").write_text(text.format(ratio))
        sweeps.append(load_sweep(tmp_path / f"{name}.toml"))
    pair = PairSource(left=str(scene), scene=True)
    with ResultStore(tmp_path / "runs.sqlite") as store:
        store.add_pairs([pair])
        run = store.start_run("test", "v", {}, "")
        for sweep in sweeps:
            store.add_configs([c.record() for c in sweep.configs])
            for number, config in enumerate(sweep.configs):
                store.write_task(config.config_id, run, [(pair.pair_id, PairEvaluation("Teddy", "OK",
                                                                                        acc_r_min_pct=90.0 + number))])
        labels = [s["label"] for s in config_summaries(store)]
        header, rows = csv_table(store)
    assert labels == [f"segmentation.kernel_size={k} max_ratio={r}" for r in (0.7, 0.9) for k in (3, 5)]
    assert sorted(row[header.index("label")] for row in rows) == sorted(labels)
    assert main(["results", str(tmp_path / "runs.sqlite")]) == 0
    assert "segmentation.kernel_size=3 max_ratio=0.9 (default, 128x96)" in capsys.readouterr().out
    # Labels that already differ stay as they were: a single sweep's grid.
    with ResultStore(tmp_path / "one.sqlite") as store:
        store.add_configs([c.record() for c in sweeps[0].configs])
        assert [c["label"] for c in store.configs()] == ["segmentation.kernel_size=3", "segmentation.kernel_size=5"]
        assert list(distinct_labels(store.configs()).values()) == ["segmentation.kernel_size=3",
                                                                   "segmentation.kernel_size=5"]


def test_a_full_disk_is_the_runs_failure_naming_the_store(tmp_path, monkeypatch, capsys):
    """Found by filling a 1 MB tmpfs: a store that could not be made on a full disk was "not a results store" (a
    usage error, exit 2) and left its 4 KB file and journal behind; rows that could not be written were an
    "internal error ... please report it". Both are now an OSError naming the store (exit 1); a failed new store
    leaves nothing, a failed task commits none of its rows. (SQLite's page limit stands in for the disk.)"""
    from svs_torch.data import PairSource
    from svs_torch.evaluation import PairEvaluation
    from svs_torch.evaluation.store import ResultStore
    from svs_torch.evaluation.sweep import make_sweep_config

    pairs = [PairSource(left=f"scene{i}", scene=True) for i in range(40)]
    config = make_sweep_config("default", {}, None, "default")
    path = tmp_path / "runs.sqlite"
    with ResultStore(path) as store:
        store.add_pairs(pairs)
        store.add_configs([config.record()])
        run = store.start_run("test", "v", {}, "")
        pages = store.connection.execute("PRAGMA page_count").fetchone()[0]
        store.connection.execute(f"PRAGMA max_page_count = {pages}")
        rows = [(p.pair_id, PairEvaluation(p.name, "OK", reason="x" * 2000)) for p in pairs]
        with pytest.raises(OSError, match=f"db: cannot write {path}: database or disk is full"):
            store.write_task(config.config_id, run, rows)
        assert store.results() == [] and not store.connection.in_transaction
    assert main(["results", str(path)]) == 0  # what was committed reads as before
    capsys.readouterr()

    def full(self):
        error = sqlite3.OperationalError("database or disk is full")
        error.sqlite_errorcode = 13
        sqlite3.connect(self.path).close()  # the file sqlite made before the disk filled
        raise error

    monkeypatch.setattr(ResultStore, "_connect_to_write", full)
    with pytest.raises(OSError, match="db: cannot write .*new.sqlite: database or disk is full"):
        ResultStore(tmp_path / "new.sqlite")
    assert not (tmp_path / "new.sqlite").exists()
    with pytest.raises(OSError, match="cannot write"):  # an existing store is kept, whatever failed
        ResultStore(path)
    assert path.is_file()


def test_an_error_row_is_run_again_on_resume_and_replaced(tmp_path):
    """Found by a review of the evaluation: an ERROR row (a run that raised: out of memory, a full disk under an
    export) counted as done, so resuming a sweep never ran it again. Other stored rows are still kept as they are."""
    from svs_torch.data import PairSource
    from svs_torch.evaluation import PairEvaluation
    from svs_torch.evaluation.store import ResultStore
    from svs_torch.evaluation.sweep import make_sweep_config

    pairs = [PairSource(left=f"scene{i}", scene=True) for i in range(2)]
    config = make_sweep_config("default", {}, None, "default")
    with ResultStore(tmp_path / "runs.sqlite") as store:
        store.add_pairs(pairs)
        store.add_configs([config.record()])
        run = store.start_run("test", "v", {}, "")
        store.write_task(config.config_id, run, [(pairs[0].pair_id, PairEvaluation("a", "ERROR", reason="MemoryError")),
                                                 (pairs[1].pair_id, PairEvaluation("b", "OK", acc_r_min_pct=90.0))])
        assert store.done() == {(config.config_id, pairs[1].pair_id)}
        written = store.write_task(config.config_id, run, [
            (pairs[0].pair_id, PairEvaluation("a", "OK", acc_r_min_pct=97.0)),
            (pairs[1].pair_id, PairEvaluation("b", "OK", acc_r_min_pct=10.0))])
        assert written == 1 and len(store.done()) == 2
        rows = {row["name"]: row for row in store.results()}
    assert (rows["a"]["status"], rows["a"]["acc_r_min_pct"]) == ("OK", 97.0) and rows["b"]["acc_r_min_pct"] == 90.0


def test_results_rank_nominal_only_configurations_on_their_nominal_means(reference, tmp_path, capsys):
    """A sweep over scenes that ship no calibration has no headline accuracy (nominal pairs are reported apart):
    its configurations are still ranked, on their nominal means, and the summary says so."""
    db = tmp_path / "nominal.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("UPDATE results SET calibrated = 0")
    assert main(["results", str(db), "--sort", "acc_objects_pct"]) == 0
    out = capsys.readouterr().out
    assert "nominal calibration" in out
    summaries = json.loads((main(["results", str(db), "--json"]), capsys.readouterr().out)[1])["configs"]
    order = sorted(summaries, key=lambda s: -s["nominal_calibration"]["acc_objects_pct"])
    rows = [line.split()[0] for line in out.splitlines() if line[:16] in {s["config_id"] for s in summaries}]
    assert rows == [s["config_id"] for s in order]
    # Found by a review of the evaluation: the figure and "best by each metric" read the headline means alone, so
    # for such a sweep the figure's parameter panels were empty and its per-scene bars showed the first
    # configuration, not the best the table ranked.
    from svs_torch.evaluation.report import best_by_metric, results_figure
    from svs_torch.evaluation.store import ResultStore

    assert "Acc objects %" in out.split("best by each metric:")[1]
    with ResultStore(db) as store:
        figure = results_figure(store)
        best = dict((key, pick) for key, _, pick in best_by_metric(summaries))["acc_objects_pct"]
    assert best["config_id"] == order[0]["config_id"]
    panels = [axis for axis in figure.axes if axis.get_ylabel().startswith("mean Acc")]
    assert panels and all(line.get_ydata().size and not np.isnan(line.get_ydata()).all() for axis in panels
                          for line in axis.get_lines())
    assert best["label"] in figure.axes[-1].get_title()
    assert figure.axes[-1].get_ylim()[1] <= 100.0  # no accuracy passes 100 % (the axis went to about 104, an audit)


def test_results_rank_over_the_larger_group_and_json_keeps_sort_and_top(reference, tmp_path, capsys):
    """Found by an audit of the bulk commands: over 26 Middlebury 2005/2006 scenes, one of which ships its own
    calibration, `results` ranked (and named best) by that one pair while the table said 26; and --json ignored
    --sort and --top."""
    db = tmp_path / "mostly_nominal.sqlite"
    with edited_copy(reference, db) as connection:
        first = connection.execute("SELECT min(pair_id) FROM results").fetchone()[0]
        connection.execute("UPDATE results SET calibrated = 0 WHERE pair_id != ?", (first,))
    assert main(["results", str(db), "--json", "--top", "0"]) == 0
    summaries = json.loads(capsys.readouterr().out)["configs"]
    assert all(s["scored"] == 1 and s["nominal_calibration"]["scored"] == 3 for s in summaries)
    by_nominal = sorted(summaries, key=lambda s: -s["nominal_calibration"]["acc_objects_pct"])
    assert [s["config_id"] for s in summaries] == [s["config_id"] for s in by_nominal]  # best first, as the table
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line[:16].strip() in {s["config_id"] for s in summaries}]
    assert [row[0] for row in rows] == [s["config_id"] for s in by_nominal] and all(row[3:5] == ["3", "n"]
                                                                                    for row in rows)
    assert float(rows[0][7]) == round(by_nominal[0]["nominal_calibration"]["acc_objects_pct"], 1)
    assert "'n': scored with a nominal calibration" in out
    assert main(["results", str(db), "--json", "--top", "1", "--sort", "acc_r_min_pct"]) == 0
    picked = json.loads(capsys.readouterr().out)
    best_r_min = max(summaries, key=lambda s: s["nominal_calibration"]["acc_r_min_pct"])
    assert picked["sort"] == "acc_r_min_pct" and [s["config_id"] for s in picked["configs"]] == [
        best_r_min["config_id"]]
    # "best" is over every configuration, as the text's "best by each metric" (it was over the --top listed, and
    # named another configuration than the text: an audit)
    from svs_torch.evaluation.report import METRICS, best_by_metric
    assert picked["best"] == {key: pick["config_id"] for key, _, pick in best_by_metric(summaries)}
    assert len(set(picked["best"].values())) > 1
    assert main(["results", str(db), "--top", "1"]) == 0
    text = capsys.readouterr().out.split("best by each metric:")[1].splitlines()
    named = {key: line.strip()[len(label):].split()[1] for key, label, _ in METRICS for line in text
             if line.strip().startswith(label)}
    assert named == picked["best"]


def test_a_swept_optional_sub_setting_reads_as_its_swept_value():
    """Found by an audit of the bulk commands: `refine_matches = [true, false]` came out in the CSV and the figure's
    ticks as the whole settings dict (a Python repr) and an empty cell. Later: the preset's own setting, switched
    on, read "on", so results --figure drew it as a tick apart from the same setting swept as true; it reads True."""
    from svs_torch.evaluation.report import parameter_value

    on = {"overrides": {"refine_matches": True}, "config": {"refine_matches": {"radius_scales": 1.5}, "seed": 0}}
    off = {"overrides": {"refine_matches": False}, "config": {"refine_matches": None, "seed": 0}}
    default = {"overrides": {}, "config": {"refine_matches": {"radius_scales": 1.5}, "seed": 0}}
    assert [parameter_value(c, "refine_matches") for c in (on, off, default)] == [True, False, True]
    assert parameter_value({"overrides": {}, "config": {"dense": {"window_size": 9}}}, "dense.window_size") == 9


def test_results_rank_every_configuration_over_one_group(reference, tmp_path, capsys):
    """A review: each configuration chose its own group, so one measured on fewer pairs (its own-calibration mean)
    was ranked against the others' nominal means under one heading."""
    db = tmp_path / "mixed.sqlite"
    with edited_copy(reference, db) as connection:
        first = connection.execute("SELECT min(pair_id) FROM results").fetchone()[0]
        last = connection.execute("SELECT max(config_id) FROM results").fetchone()[0]
        connection.execute("UPDATE results SET calibrated = 0 WHERE pair_id != ?", (first,))
        connection.execute("DELETE FROM results WHERE config_id = ? AND pair_id != ?", (last, first))
    assert main(["results", str(db), "--json"]) == 0
    summaries = {s["config_id"]: s for s in json.loads(capsys.readouterr().out)["configs"]}
    assert {s["ranked_group"] for s in summaries.values()} == {"nominal"}
    assert summaries[last]["scored"] == 1 and summaries[last]["nominal_calibration"]["scored"] == 0
    assert main(["results", str(db)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line[:16].strip() in summaries]
    assert rows[-1][0] == last and rows[-1][3:6] == ["0", "n", "-"]  # no nominal pair: last, its means '-'


@pytest.mark.skipif(not Path("/dev/null").exists(), reason="needs /dev/null")
@pytest.mark.parametrize("command", ["eval", "results"])
def test_a_device_is_refused_as_a_results_store_before_sqlite_touches_it(data_dir, capsys, command):
    """Was (an audit of bad outputs): --db /dev/null failed only after sqlite had made /dev/null-journal beside
    it (as root, in /dev), and results called the device a folder. Now one line, before any file is made."""
    journal = Path("/dev/null-journal")
    existed = journal.exists()
    argv = ["eval", str(data_dir / "middlebury_2001"), "--db", "/dev/null"] if command == "eval" else \
        ["results", "/dev/null"]
    assert main(argv) == 2
    named = "--db" if command == "eval" else "FILE.sqlite"
    assert f"{named}: expected a results file, got a device or other special file: /dev/null" in capsys.readouterr().err
    assert journal.exists() == existed


@pytest.mark.parametrize("argv, message", [
    (["results", ""], "svs-depth results: error: FILE.sqlite: expected a results file name, got ''"),
    (["sweep", "", "--db", "s.sqlite"], "svs-depth sweep: error: SWEEP.toml: expected a sweep file name, got ''"),
])
def test_an_empty_file_name_is_refused_as_such_not_as_the_current_folder(tmp_path, monkeypatch, capsys, argv,
                                                                          message):
    """An audit of careless arguments: 'results "$DB"' with DB unset said "expected a results file, got a folder: ."
    and 'sweep "$FILE"' ".: expected a TOML file, got a folder", naming a folder nobody gave."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert capsys.readouterr().err.strip().splitlines() == [message]
    assert list(tmp_path.iterdir()) == []


def test_the_stores_errors_name_the_db_option(data_dir, tmp_path, monkeypatch, capsys):
    """Found by an audit of the command line: `eval` and `sweep` said "db: the folder nodir does not exist", the
    library's argument, where every other error names the option the user typed."""
    monkeypatch.chdir(tmp_path)
    sweep_file = write_sweep(tmp_path, data_dir)
    for argv in (["eval", str(data_dir / "middlebury_2001"), "--db", "nodir/x.sqlite"],
                 ["sweep", str(sweep_file), "--db", "nodir/x.sqlite", "--workers", "0"]):
        assert main(argv) == 2
        assert capsys.readouterr().err == f"svs-depth {argv[0]}: error: --db: the folder nodir does not exist\n"
    assert not (tmp_path / "nodir").exists()


def test_results_errors_name_the_store_as_the_usage_line_does(tmp_path, capsys):
    """Found by an audit of the command line: 'svs-depth results' said "db: expected a results file, ...", the
    library's argument, where its usage line shows the store as FILE.sqlite (eval and sweep name --db)."""
    from svs_torch.evaluation.store import ResultStore

    not_store, empty = tmp_path / "notes.txt", tmp_path / "empty.sqlite"
    not_store.write_text("not a store")
    ResultStore(empty).close()
    for argv, reason in ((["results", str(tmp_path / "missing.sqlite")], "expected a results file, got no file"),
                         (["results", str(not_store)], f"{not_store} is not a results store"),
                         (["results", str(empty), "--figure", str(tmp_path / "f.png")], f"{empty} holds no results")):
        assert main(argv) == 2
        assert capsys.readouterr().err.startswith(f"svs-depth results: error: FILE.sqlite: {reason}")


@pytest.mark.parametrize("option", ["--csv", "--figure"])
def test_results_name_the_option_and_file_a_full_disk_refused(reference, tmp_path, capsys, monkeypatch, option):
    """Was (an audit of full disks): 'svs-depth results: error: No space left on device', naming neither the
    option nor the file, where estimate, eval, calibrate and sweep name both."""
    import contextlib

    import svs_torch.core.files as files
    import svs_torch.evaluation.report as report

    @contextlib.contextmanager
    def full_disk(path, *args, **kwargs):
        raise OSError(28, "No space left on device")
        yield  # noqa: unreachable -- a generator, as atomic_output is

    monkeypatch.setattr(files, "atomic_output", full_disk)
    monkeypatch.setattr(report, "atomic_output", full_disk)
    _, db = reference
    target = tmp_path / ("rows.csv" if option == "--csv" else "results.png")
    assert main(["results", str(db), option, str(target)]) == 1
    assert f"{option}: cannot write '{target}': No space left on device" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_the_figure_says_a_tie_for_best_and_that_its_axes_are_zoomed(reference, tmp_path):
    """Found by an audit of the figures: two configurations at the same 99.7 % were one "best" alone, and the
    parameter panels' axis, fitted to a 0.03-point spread, did not say it was zoomed."""
    from svs_torch.evaluation.report import results_figure
    from svs_torch.evaluation.store import ResultStore

    db = tmp_path / "tied.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("UPDATE results SET acc_objects_pct = 99.0 WHERE acc_objects_pct IS NOT NULL")
    with ResultStore(db) as store:
        figure = results_figure(store)
        configs = len({row["config_id"] for row in store.results()})
    assert configs > 1 and f"tied with {configs - 1} other" in figure.axes[-1].get_title().replace("\n", " ")
    assert all("zoomed" in axis.get_ylabel() for axis in figure.axes)
    with ResultStore(reference[1]) as store:
        assert "tied" not in results_figure(store).axes[-1].get_title()


def test_the_summarys_best_by_each_metric_says_an_exact_tie(reference, tmp_path, capsys):
    """Found by an audit of the results' numbers: two configurations of the same means (a parameter the pipeline
    did not use) were "best by each metric" the first stored alone, the other's equal value unsaid."""
    db = tmp_path / "tied.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("UPDATE results SET acc_objects_pct = 99.0 WHERE acc_objects_pct IS NOT NULL")
    assert main(["results", str(db)]) == 0
    lines = capsys.readouterr().out.split("best by each metric:")[1].splitlines()
    line = next(line for line in lines if line.strip().startswith("Acc objects %"))
    assert line.endswith("(tied with 2 others)")
    assert not any("tied" in line for line in lines if line.strip().startswith("s per pair"))


def test_results_name_the_settings_every_configuration_ran_with_beyond_its_label(reference, tmp_path, capsys):
    """Found by an audit of the results' numbers: a sweep's [set] values (dense.window_size = 7 for every
    configuration) were in no label, so its summary read as one of the preset's window, and a sweep whose only
    setting was [set] read "(preset)"."""
    db = tmp_path / "fixed.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("UPDATE configs SET overrides = json_set(overrides, '$.\"dense.window_size\"', 7)")
    assert main(["results", str(db)]) == 0
    assert capsys.readouterr().out.splitlines()[1] == ("every configuration also ran with (not in its label): "
                                                       "dense.window_size=7")
    assert main(["results", str(reference[1])]) == 0
    assert "also ran with" not in capsys.readouterr().out


def test_results_say_which_configurations_gave_the_same_results(reference, tmp_path, capsys):
    """Found by an audit of the results' numbers: a sweep over a setting the configuration in use never reads
    (segmentation.foreground under the nearness segmenter) ran its values as configurations of identical rows,
    ranked apart and one named best, and nothing said they were one. Here the second configuration's rows are
    made the first's, times and run aside."""
    db = tmp_path / "same.sqlite"
    with edited_copy(reference, db) as connection:
        first, second, third = [c for (c,) in connection.execute("SELECT config_id FROM configs ORDER BY rowid")]
        columns = [name for (name,) in connection.execute("SELECT name FROM pragma_table_info('results')")]
        copied = [dict(zip(columns, row)) for row in
                  connection.execute("SELECT * FROM results WHERE config_id = ?", (first,))]
        connection.execute("DELETE FROM results WHERE config_id = ?", (second,))
        for row in copied:
            row.update(config_id=second, time_s=row["time_s"] * 1.5, run_id=None)
            connection.execute(f"INSERT INTO results ({', '.join(map(repr, columns))}) VALUES "
                               f"({', '.join('?' * len(columns))})", list(row.values()))
    assert main(["results", str(db)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "the same results on every pair" in line]
    assert len(notes) == 1 and notes[0].startswith(f"note: {first} (") and f" = {second} (" in notes[0]
    assert third not in notes[0]
    assert main(["results", str(db), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["same_results"] == [[first, second]]
    assert main(["results", str(reference[1]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["same_results"] == []


def test_results_say_the_nominal_pairs_kept_apart_from_the_means(reference, tmp_path, capsys):
    """Found by an audit of the results' numbers: a sweep over 5 scenes, one shipping no calibration (Middlebury
    2005/2006 Books), read 'scored 4' with no word of the fifth; eval says it is scored apart, below."""
    db = tmp_path / "one_nominal.sqlite"
    with edited_copy(reference, db) as connection:
        first = connection.execute("SELECT min(pair_id) FROM results").fetchone()[0]
        connection.execute("UPDATE results SET calibrated = 0 WHERE pair_id = ?", (first,))
    assert main(["results", str(db)]) == 0
    out = capsys.readouterr().out
    assert "1 more per configuration were scored with a nominal one" in out and "nominal_calibration" in out
    assert main(["results", str(reference[1])]) == 0
    assert "nominal" not in capsys.readouterr().out


def test_results_say_when_disparity_means_are_over_fewer_pairs(reference, tmp_path, capsys):
    """Found by an audit of the results' numbers: the accuracies count a failed pair 0 %, but d<=1, prec, bad-2 and
    D1 are means over the pairs that have them; a configuration that failed on a pair was ranked on them over the
    others it kept, without a word."""
    db = tmp_path / "fewer.sqlite"
    with edited_copy(reference, db) as connection:
        first = connection.execute("SELECT min(pair_id) FROM results").fetchone()[0]
        last = connection.execute("SELECT max(config_id) FROM results").fetchone()[0]
        kept = [name for (name,) in connection.execute("SELECT name FROM pragma_table_info('results')")
                if name.startswith("kept_all_")]
        connection.execute("UPDATE results SET status = 'NO_DENSE_DEPTH', dense_within_1px = NULL, inlier_precision "
                           f"= NULL, {', '.join(f'{name} = NULL' for name in kept)} WHERE config_id = ? AND "
                           "pair_id = ?", (last, first))
    assert main(["results", str(db)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note: d<=1")]
    assert len(notes) == 1 and f"({last} d<=1 over 3 of 4, prec over 3 of 4, bad-2/D1 over 3 of 4)" in notes[0]
    assert main(["results", str(reference[1])]) == 0
    assert "note: d<=1" not in capsys.readouterr().out


def test_the_parameter_panels_ticks_are_the_values_as_the_csv_has_them(reference, tmp_path):
    """Found by an audit of the results' numbers: a swept text value (a weights path, learned:PATH) was ticked by
    its repr with the quotes stripped, so an apostrophe kept the quotes and a backslash was doubled."""
    from svs_torch.evaluation.report import results_figure
    from svs_torch.evaluation.store import ResultStore

    db, odd = tmp_path / "odd.sqlite", "learned:/w/o'brien\\net, é.pt"
    with edited_copy(reference, db) as connection:
        last = connection.execute("SELECT max(config_id) FROM results").fetchone()[0]
        connection.execute("UPDATE configs SET config = json_set(config, '$.segmentation.kernel_size', ?) WHERE "
                           "config_id = ?", (odd, last))
    with ResultStore(db) as store:
        panel = next(axis for axis in results_figure(store).axes if axis.get_ylabel().startswith("mean Acc"))
    assert odd in [label.get_text() for label in panel.get_xticklabels()]
    assert main(["results", str(db), "--csv", str(tmp_path / "odd.csv")]) == 0
    assert odd in (tmp_path / "odd.csv").read_text(encoding="utf-8")


def test_the_figure_of_a_stopped_sweep_says_its_means_are_over_the_rows_stored(reference, tmp_path):
    """Found by an audit of the results' numbers: the summary notes configurations without rows and ones that lack
    pairs the others have, but the figure's panels averaged over whatever had rows (different parts of the grid, or
    of the pairs) under a title of "N configurations", unsaid."""
    from svs_torch.evaluation.report import results_figure
    from svs_torch.evaluation.store import ResultStore

    with ResultStore(reference[1]) as store:
        assert results_figure(store).get_suptitle() == "reference.sqlite: 3 configurations"
    db = tmp_path / "stopped.sqlite"
    with edited_copy(reference, db) as connection:
        first, last = connection.execute("SELECT min(config_id), max(config_id) FROM results").fetchone()
        connection.execute("DELETE FROM results WHERE config_id = ?", (last,))
        connection.execute("DELETE FROM results WHERE config_id = ? AND pair_id = (SELECT min(pair_id) FROM "
                           "results)", (first,))
    with ResultStore(db) as store:
        title = results_figure(store).get_suptitle()
    assert title.startswith("stopped.sqlite: 2 of 3 configurations have rows, 1 of them not on every pair\n")
    assert "each mean is over the rows stored" in title
    assert main(["results", str(db), "--figure", str(tmp_path / "stopped.png")]) == 0


def test_the_figure_of_a_store_without_rows_names_its_argument(tmp_path):
    """Found by an audit of the library's errors: results_figure(store) and plot_results(store, path) of a store
    without rows said "db: ... holds no results yet", an argument neither function has."""
    from svs_torch.evaluation.report import plot_results, results_figure
    from svs_torch.evaluation.store import ResultStore

    with ResultStore(tmp_path / "empty.sqlite") as store:
        said = f"^store: {re.escape(str(tmp_path / 'empty.sqlite'))} holds no results yet$"
        for call in (lambda: results_figure(store), lambda: plot_results(store, tmp_path / "f.png")):
            with pytest.raises(InputError, match=said):
                call()


def test_the_parameter_panels_never_pass_100_pct(reference, tmp_path):
    """Found by an audit of the results' numbers: a swept parameter without effect (equal means at 99.8 %) had its
    panel autoscaled to 94-105 %, room above the best that no accuracy has."""
    from svs_torch.evaluation.report import results_figure
    from svs_torch.evaluation.store import ResultStore

    db = tmp_path / "flat.sqlite"
    with edited_copy(reference, db) as connection:
        connection.execute("UPDATE results SET acc_r_min_pct = 99.8, acc_r_max_pct = 99.8, acc_objects_pct = 99.8")
    with ResultStore(db) as store:
        panels = [axis for axis in results_figure(store).axes if axis.get_ylabel().startswith("mean Acc")]
    assert panels and all(axis.get_ylim()[1] <= 100.0 and axis.get_ylim()[0] < 99.8 for axis in panels)


def test_the_scene_bars_follow_the_summarys_rules_for_pairs_without_truth_and_failed_ones(reference, tmp_path):
    """Found by an audit of the results' numbers: a pair without ground truth (a listed pair, in no mean of the
    summary) was drawn as 0 % bars, read as a measured 0, and its zeros set the zoomed axis to 0-100."""
    from svs_torch.evaluation.report import results_figure
    from svs_torch.evaluation.store import ResultStore

    db = tmp_path / "no_truth.sqlite"
    with edited_copy(reference, db) as connection:
        first = connection.execute("SELECT min(pair_id) FROM results").fetchone()[0]
        connection.execute("UPDATE results SET has_truth = 0, status = 'NO_DENSE_DEPTH', acc_r_min_pct = NULL, "
                           "acc_r_max_pct = NULL, acc_objects_pct = NULL WHERE pair_id = ?", (first,))
    with ResultStore(db) as store:
        axis = results_figure(store).axes[-1]
    ticks = [label.get_text() for label in axis.get_xticklabels()]
    heights = np.array([[bar.get_height() for bar in bars] for bars in axis.containers])
    assert sum(tick.endswith(" (NO_DENSE_DEPTH, no truth)") for tick in ticks) == 1
    assert np.isnan(heights).sum() == 3 and np.nanmin(heights) > 50 and axis.get_ylim()[0] > 50
    with edited_copy(reference, db) as connection:  # a failed pair with ground truth counts 0 %, and says why
        connection.execute("UPDATE results SET status = 'ERROR', acc_r_min_pct = NULL, acc_r_max_pct = NULL, "
                           "acc_objects_pct = NULL WHERE pair_id = ?", (first,))
    with ResultStore(db) as store:
        axis = results_figure(store).axes[-1]
    assert sum(label.get_text().endswith(" (ERROR)") for label in axis.get_xticklabels()) == 1
    assert sorted(bar.get_height() for bars in axis.containers for bar in bars)[:3] == [0.0] * 3


def test_a_store_of_many_pairs_shows_their_accuracies_sorted_not_a_bar_group_each(reference, tmp_path):
    """Found by an audit of bulk evaluation: results --figure drew a group of three bars a pair, 9 845 px wide for 400
    pairs and 77 605 px for 3 200. Past MAX_SCENE_BARS pairs the panel sorts each accuracy over the pairs, names the
    lowest, and the figure is no wider for them."""
    from svs_torch.evaluation.pair_spread import MAX_SCENE_BARS
    from svs_torch.evaluation.report import results_figure
    from svs_torch.evaluation.store import ResultStore

    db = tmp_path / "many.sqlite"
    with edited_copy(reference, db) as connection:
        columns = [row[1] for row in connection.execute("PRAGMA table_info(results)")]
        pair_columns = [row[1] for row in connection.execute("PRAGMA table_info(pairs)")]
        for copy in range(1, 40):  # each pair 40 times over: 4 scenes' rows become 160 a configuration
            copied = ", ".join(f"{c} || {copy}" if c in ("pair_id", "name") else c for c in pair_columns)
            connection.execute(f"INSERT INTO pairs SELECT {copied} FROM pairs WHERE pair_id NOT GLOB '*[0-9]'")
            values = ", ".join(f"{c} || {copy}" if c == "pair_id" else
                               f"acc_objects_pct - {copy} * 0.1" if c == "acc_objects_pct" else c for c in columns)
            connection.execute(f"INSERT INTO results SELECT {values} FROM results WHERE pair_id NOT GLOB '*[0-9]'")
    with ResultStore(db) as store:
        per_config = max(sum(r["config_id"] == c["config_id"] for r in store.results()) for c in store.configs())
        figure = results_figure(store)
    assert per_config > MAX_SCENE_BARS
    axis = figure.axes[-1]
    assert not axis.containers and len(axis.lines) == 3 and axis.get_title().startswith(f"over {per_config} pairs")
    assert [len(line.get_xdata()) for line in axis.lines] == [per_config] * 3
    objects = axis.lines[2].get_ydata()
    assert list(objects) == sorted(objects) and "lowest by objects: " in axis.texts[0].get_text()
    assert figure.get_figwidth() <= 10.4  # two columns of 5.2 in: the swept parameter beside the pairs


def test_a_pool_left_by_ctrl_c_waits_for_nothing_and_leaves_no_process():
    """Found by an audit of sweeps: a first Ctrl-C or SIGTERM, often one that came while the pool was starting, left
    `sweep` hung until a second one (10 of 14 signals), in the orderly shutdown's waits for the workers and the
    forkserver. Left by an exception, the pool now cancels, kills and waits for nothing: here the two 30 s tasks
    running when Ctrl-C comes are not waited for."""
    import multiprocessing
    import time
    from multiprocessing import forkserver

    from svs_torch.evaluation.executors import map_process_pool

    results = map_process_pool(time.sleep, [0.0, 30.0, 30.0, 30.0], workers=2, threads=1)
    assert next(results) is None  # the first task is done: the others run
    started = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        results.throw(KeyboardInterrupt())
    assert time.monotonic() - started < 10.0
    assert not [p for p in multiprocessing.active_children() if p.is_alive()]
    assert getattr(getattr(forkserver, "_forkserver", None), "_forkserver_pid", None) is None


def test_a_second_sweep_on_a_store_being_written_is_refused(reference, tmp_path):
    """Found by an audit of sweeps: two sweeps on one store each ran every task (the rows right, the work done
    twice) without a word. A sweep holds its configurations while it writes the store; the hold goes with the
    process. Found by an audit of two processes at once: a sweep of other configurations (another grid, a job
    array's other part) was refused too; it now runs beside it."""
    from svs_torch.evaluation.store import ResultStore
    from svs_torch.evaluation.sweep import load_sweep, run_sweep

    db = tmp_path / "held.sqlite"
    shutil.copyfile(reference[1], db)
    sweep = load_sweep(reference[0])
    with ResultStore(db) as other:
        other.claim_for_a_sweep([sweep.configs[1].config_id, "another grid's"])
        with pytest.raises(InputError, match=rf"^db: another run \(a sweep or an eval --db\) is writing {db} and "
                                             "running 1 of this run's 3 configurations; run this one once it has ended"):
            run_sweep(sweep, db, workers=0)
        with ResultStore(db) as beside:  # another grid: held beside it
            beside.claim_for_a_sweep(["a third grid's"])
    outcome = run_sweep(sweep, db, workers=0)  # released on close: nothing left to run
    assert outcome.tasks == 0


HOLDER = """\
import sys
from svs_torch.evaluation.store_access import claim_configs
held = claim_configs(sys.argv[1], sys.argv[2:])
print("held", flush=True)
sys.stdin.read()
"""


@pytest.mark.skipif(not (os.name == "posix" and hasattr(__import__("fcntl"), "F_OFD_SETLK")),
                    reason="needs open-file-description locks (Linux)")
def test_a_sweep_held_by_another_process_is_refused_until_it_is_killed(reference, tmp_path, capsys):
    """Another process holds the sweep's configurations: the sweep is refused with one line, results says a
    sweep is writing; killed with SIGKILL, the hold is gone and the same sweep runs (nothing left to run)."""
    sweep_file, stored = reference
    db = tmp_path / "shared.sqlite"
    shutil.copyfile(stored, db)
    ids = [c.config_id for c in load_sweep(sweep_file).configs]
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(db), ids[0]], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(Path(svs_torch.__file__).parents[1])})
    try:
        assert holder.stdout.readline() == "held\n"
        assert main(["sweep", str(sweep_file), "--db", str(db), "--workers", "0"]) == 2
        assert "error: --db: another run (a sweep or an eval --db) is writing" in capsys.readouterr().err
        assert main(["results", str(db), "--json"]) == 0
        assert (f"note: a sweep or an eval --db is writing {db} now; these are the rows stored so far"
                in capsys.readouterr().err)
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    assert main(["sweep", str(sweep_file), "--db", str(db), "--workers", "0"]) == 0
    assert "0 rows written by 0 tasks, 12 of 12 stored" in capsys.readouterr().err
    assert main(["results", str(db), "--json"]) == 0
    assert "is writing" not in capsys.readouterr().err


def test_a_sweep_in_this_process_gives_back_the_callers_torch_threads(data_dir, tmp_path):
    """Found by an audit of the API's effect on its caller: `run_sweep(..., workers=0, threads=T)` ran its tasks in
    the calling process and left torch there on T threads: a notebook's training after a small sweep ran on one
    thread of its machine's cores, without a word."""
    path = tmp_path / "one.toml"
    path.write_text(f'paths = ["{data_dir / "middlebury_eval3_Q" / "Teddy"}"]\nsize = "160x120"\n')
    before = torch.get_num_threads()
    asked = 2 if before == 1 else 1
    try:
        outcome = run_sweep(load_sweep(path), tmp_path / "one.sqlite", workers=0, threads=asked, warn=pytest.fail)
        after = torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
    assert outcome.rows_written == 1
    assert after == before


@pytest.mark.parametrize("change, message", [
    (dict(batch_size=0), "sweep: batch_size: expected an integer of at least 1, got 0"),
    (dict(batch_size=-1), "sweep: batch_size: expected an integer of at least 1, got -1"),
    (dict(batch_size="2"), "sweep: batch_size: expected an integer of at least 1, got '2'"),
    (dict(size_wh=(0, 120)), "sweep: size_wh: expected None or (width, height), two ints from 1 to 8192, got (0, "),
    (dict(size_wh=(100000, 120)), "sweep: size_wh: expected None or (width, height), two ints from 1 to 8192, got "),
    (dict(size_wh=(True, 120)), "sweep: size_wh: expected None or (width, height), two ints from 1 to 8192, got "),
    (dict(size_wh=None), "sweep: configs: '(preset)' was made for the size 160x120, the sweep's is native"),
    (dict(sources="Teddy"), "sweep: sources: expected a list of PairSource (read_pair_sources), got 'Teddy'"),
    (dict(workers=-1), "sweep: workers: expected an integer of at least 0, got -1"),
    (dict(threads=0), "sweep: threads: expected an integer of at least 1, got 0"),
])
def test_a_sweep_built_by_hand_with_odd_values_is_refused_by_name_before_a_store_is_made(data_dir, tmp_path, change,
                                                                                          message):
    """Found by an audit of the Python API: a Sweep built in code with a batch_size of 0 failed in range() (one of
    -1 ran nothing and reported success), a size of (0, 120) in the resampler, workers=-1 in the process pool,
    each after the store had been made and held the run."""
    from svs_torch.data import read_pair_sources
    from svs_torch.evaluation.sweep import make_sweep, make_sweep_config

    sources = read_pair_sources([data_dir / "middlebury_eval3_Q" / "Teddy"])
    sweep = make_sweep(sources, [make_sweep_config("default", {}, (160, 120))], (160, 120))
    options = {key: change.pop(key) for key in ("workers", "threads") if key in change}
    db = tmp_path / "odd.sqlite"
    with pytest.raises(InputError) as error:
        run_sweep(dataclasses.replace(sweep, **change), db, workers=options.get("workers", 0),
                  threads=options.get("threads"))
    assert str(error.value).startswith(message)
    assert not db.exists()


def test_a_sweep_made_in_code_from_a_folders_name_is_refused_by_name(data_dir):
    """Found by an audit of the Python API: make_sweep given a folder's name for its pairs read it letter by letter,
    to "'str' object has no attribute 'problem'"."""
    from svs_torch.evaluation.sweep import make_sweep, make_sweep_config

    config = make_sweep_config("default", {}, None)
    with pytest.raises(InputError, match="sweep: sources: expected a list of PairSource"):
        make_sweep(str(data_dir / "middlebury_eval3_Q"), [config], None)
    with pytest.raises(InputError, match="sweep: configs: expected a list of SweepConfig"):
        make_sweep([], [config.record()], None)


def test_plot_results_refuses_a_bad_path_by_name_before_drawing(reference, tmp_path):
    """Found by an audit of the Python API: plot_results to a folder or a .txt was matplotlib's "Format '' is not
    supported", to a missing folder a FileNotFoundError naming its temporary file, to None a TypeError; a .jpg,
    which matplotlib writes, is still written."""
    from svs_torch.evaluation.report import plot_results
    from svs_torch.evaluation.store import ResultStore

    with ResultStore(reference[1], create=False) as store:
        for path, message in [(tmp_path, "path: expected a file name, got the folder"),
                              (tmp_path / "plot.txt", r"path: expected an image \(.*\.png.*\) file name"),
                              (tmp_path / "none" / "plot.png", "path: folder .* does not exist"),
                              (None, r"path: expected a file name \(str or os.PathLike\), got NoneType")]:
            with pytest.raises(InputError, match=message):
                plot_results(store, path)
        assert plot_results(store, tmp_path / "plot.jpg").stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plot.jpg"]
