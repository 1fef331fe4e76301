"""The kernels' compile cache (svs_torch.core.kernels.loader): a folder others can write to is refused and nothing in
it is loaded; the library names hold the flags actually used, the compiler and the CPU; a failed, hanging or
unloadable build is remembered, so a later process neither retries it nor says more than one line. Each test has
its own cache folder and starts as a new process would (:func:`_new_process`); the fake compilers are shell
scripts that log their calls and hand the work to the system's ``cc``."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from svs_torch.core import kernels
from svs_torch.core.kernels import loader

REAL_CC = shutil.which("cc") or shutil.which("gcc")
needs_cc = pytest.mark.skipif(REAL_CC is None, reason="no C compiler")
needs_root = pytest.mark.skipif(os.getuid() != 0, reason="giving a file to another user needs root")
#: The smallest kernel (about 0.2 s to compile).
KERNEL = "find_runs"
OTHER_UID = 12345


def _new_process(monkeypatch) -> None:
    """Forget everything the loader remembers within a process, as a new process starts."""
    monkeypatch.setattr(kernels, "_LIBRARIES", {})
    monkeypatch.setattr(loader, "_OFF", {})
    monkeypatch.setattr(loader, "_ANNOUNCED", set())
    loader.compiler_identity.cache_clear()


@pytest.fixture
def cache(monkeypatch, tmp_path) -> Path:
    """A fresh cache folder (not yet made) for this test, the system compiler, kernels on."""
    monkeypatch.setenv("SVS_TORCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.delenv("SVS_TORCH_KERNELS", raising=False)
    _new_process(monkeypatch)
    return tmp_path / "cache"


def _fake_compiler(path: Path, body: str) -> Path:
    """A shell script at ``path``: logs each call's arguments to ``path.log``, then runs ``body``."""
    path.write_text(f'#!/bin/sh\necho "$@" >> "{path}.log"\n{body}\n')
    path.chmod(0o755)
    return path


def _compiles(script: Path) -> list[str]:
    """The logged calls of a fake compiler that built something (not its ``--version``)."""
    log = Path(f"{script}.log")
    return [line for line in log.read_text().splitlines() if " -o " in line] if log.exists() else []


def _predictable_path(flags: list[str] | None = None) -> Path:
    """Where the system compiler's library of :data:`KERNEL` is looked for: the name an attacker can work out."""
    identity = loader.compiler_identity(tuple(loader.compiler_command()))
    return loader._library_path(KERNEL, flags or loader.build_flags(), identity)


def _planted_library(target: Path, sentinel: Path) -> None:
    """A library that, if ever loaded, creates ``sentinel`` (its constructor runs at load)."""
    source = target.with_name("planted.c")
    source.write_text('#include <stdio.h>\n__attribute__((constructor)) static void planted(void) {\n'
                      f'  FILE *f = fopen("{sentinel}", "w"); if (f) fclose(f);\n}}\n'
                      'int find_runs(void) { return 0; }\n')
    subprocess.run([REAL_CC, "-shared", "-fPIC", str(source), "-o", str(target)], check=True)
    source.unlink()


def _one_notice(capsys, *fragments: str) -> str:
    """The one line of stderr, which must contain each fragment and the torch paths' notice."""
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1, lines
    for fragment in ("C kernels off", "torch paths", *fragments):
        assert fragment in lines[0], lines[0]
    return lines[0]


@needs_cc
@pytest.mark.parametrize("hostile", ["mode 0777", "other owner", "symlink of another owner"])
def test_a_cache_folder_others_control_is_refused_and_nothing_in_it_loaded(cache, tmp_path, monkeypatch, capsys,
                                                                          hostile):
    """A library planted at the predictable path of a folder others can write to (or own) never runs: the
    kernels are off with one line naming the reason, and only once however many kernels are asked for."""
    if hostile != "mode 0777" and os.getuid() != 0:
        pytest.skip("giving a file to another user needs root")
    folder = tmp_path / "real" if hostile.startswith("symlink") else cache
    folder.mkdir(mode=0o700)
    target = folder / _predictable_path().name
    sentinel = tmp_path / "planted-library-ran"
    _planted_library(target, sentinel)
    target.chmod(0o755)
    if hostile == "mode 0777":
        folder.chmod(0o777)
    elif hostile == "other owner":
        os.chown(folder, OTHER_UID, -1)
    else:
        cache.symlink_to(folder)
        os.lchown(cache, OTHER_UID, -1)
    assert all(kernels.load(name) is None for name in kernels.SOURCES)
    reason = {"mode 0777": "writable by group or others (mode 777): refused",
              "other owner": f"owned by uid {OTHER_UID}, not by this user", "symlink of another owner":
              f"is a symlink owned by uid {OTHER_UID}: refused"}[hostile]
    _one_notice(capsys, str(cache), reason)
    assert not sentinel.exists()


@needs_cc
@needs_root
@pytest.mark.parametrize("hostile", ["other owner", "writable by others"])
def test_a_library_not_ours_alone_is_not_loaded(cache, tmp_path, capsys, hostile):
    """In our own private folder, a library file of another owner, or one others can write to, is not loaded."""
    cache.mkdir(mode=0o700)
    target = _predictable_path()
    sentinel = tmp_path / "planted-library-ran"
    _planted_library(target, sentinel)
    if hostile == "other owner":
        os.chown(target, OTHER_UID, -1)
        target.chmod(0o755)
    else:
        target.chmod(0o757)
    assert kernels.load(KERNEL) is None
    _one_notice(capsys, target.name, f"owned by uid {OTHER_UID}" if hostile == "other owner" else "mode 757")
    assert not sentinel.exists()


@needs_cc
def test_the_cache_folder_is_made_private_whatever_the_umask(cache, capsys):
    """Made with mode 0700 under umask 0o777 (which would leave it unusable) and the library not writable by
    others under umask 0 (the linker would make it 0777); the kernel then loads, with one announcement."""
    previous = os.umask(0o777)
    try:
        loader._private_folder(cache)
    finally:
        os.umask(0)
    try:
        assert kernels.load(KERNEL) is not None
    finally:
        os.umask(previous)
    assert oct(cache.stat().st_mode & 0o777) == oct(0o700)
    assert _predictable_path().stat().st_mode & 0o022 == 0
    assert capsys.readouterr().err.count("compiling the C kernels") == 1


@needs_cc
def test_a_failed_compile_is_remembered_with_one_notice(cache, tmp_path, monkeypatch, capsys):
    """A compiler that fails: the first process tries once with OpenMP and once serially, then says one line
    (after the compile announcement) for all 15 kernels; the next process does not call the compiler to build,
    says the same one line, and points at the marker that holds the compiler's output."""
    script = _fake_compiler(tmp_path / "broken-cc", 'echo "broken-cc: error: no such thing" >&2; exit 1')
    monkeypatch.setenv("CC", str(script))
    assert not any(kernels.available(name) for name in kernels.SOURCES)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and "compiling the C kernels" in lines[0] and "C kernels off" in lines[1], lines
    assert "broken-cc: error: no such thing" in lines[1] and len(_compiles(script)) == 2
    assert "-fopenmp" in _compiles(script)[0] and "-fopenmp" not in _compiles(script)[1]
    _new_process(monkeypatch)
    assert not any(kernels.available(name) for name in kernels.SOURCES)
    notice = _one_notice(capsys, "broken-cc: error: no such thing", "remembered in", "remove to retry")
    assert len(_compiles(script)) == 2
    marker = Path(notice.split("remembered in ")[1].split(" (remove")[0])
    assert "broken-cc: error: no such thing" in marker.read_text() and "-fopenmp" not in marker.read_text()
    marker.unlink()  # what the notice says: the next process tries again
    _new_process(monkeypatch)
    assert kernels.load(KERNEL) is None and len(_compiles(script)) == 3


@needs_cc
def test_a_hanging_compiler_costs_one_timeout_once(cache, tmp_path, monkeypatch, capsys):
    """A compile that never ends is killed with its children at the timeout (not 15 times: once), is not
    tried again serially, and the next process does not start it at all."""
    pid_file = tmp_path / "sleep.pid"
    script = _fake_compiler(tmp_path / "hanging-cc", f'[ "$1" = --version ] && exit 0\n'
                                                      f'sleep 60 & echo $! > "{pid_file}"; wait')
    monkeypatch.setenv("CC", str(script))
    monkeypatch.setattr(loader, "COMPILE_TIMEOUT_S", 1)
    started = time.monotonic()
    assert not any(kernels.available(name) for name in kernels.SOURCES)
    assert time.monotonic() - started < 10 and len(_compiles(script)) == 1
    assert "did not finish within 1 s" in capsys.readouterr().err
    sleeper = int(pid_file.read_text())
    for _ in range(100):  # the compiler's child is killed too (the process group), then reaped by init
        if not Path(f"/proc/{sleeper}").exists() or "Z" in Path(f"/proc/{sleeper}/stat").read_text().split()[2]:
            break
        time.sleep(0.02)
    else:
        pytest.fail("the hanging compiler's child still runs")
    _new_process(monkeypatch)
    assert kernels.load(KERNEL) is None and len(_compiles(script)) == 1
    _one_notice(capsys, "did not finish within 1 s")


@needs_cc
def test_cc_is_split_as_a_shell_would(cache, tmp_path, monkeypatch, capsys):
    """``CC="'<folder with a space>/cc' --tag"``: the program (quoted, with a space in its path) gets the extra
    argument first, and builds a kernel that loads."""
    (tmp_path / "a folder").mkdir()
    script = _fake_compiler(tmp_path / "a folder" / "cc", f'[ "$1" = --tag ] || exit 3\nshift\nexec {REAL_CC} "$@"')
    monkeypatch.setenv("CC", f"'{script}' --tag")
    assert kernels.load(KERNEL) is not None
    assert len(_compiles(script)) == 1 and _compiles(script)[0].startswith("--tag -O3")


def test_the_cache_key_holds_the_flags_the_compiler_and_the_cpu():
    """Serial and OpenMP builds, two compilers, two CPUs: each a different library name."""
    openmp = list(loader.FLAGS)
    serial = [flag for flag in openmp if flag != "-fopenmp"]
    names = {loader._library_path(KERNEL, flags, compiler) for flags in (openmp, serial)
             for compiler in ("gcc 12.2.0", "clang 16.0.6")}
    assert len(names) == 4
    power9 = loader._cpu_lines("processor\t: 0\ncpu\t\t: POWER9 (raw), altivec supported\nclock\t\t: 2300.000000MHz\n")
    power10 = loader._cpu_lines("processor\t: 0\ncpu\t\t: POWER10 (raw), altivec supported\nclock\t\t: 3000MHz\n")
    riscv = loader._cpu_lines("processor\t: 0\nhart\t\t: 1\nisa\t\t: rv64imafdc_zicsr\nuarch\t\t: sifive,u74-mc\n")
    assert power9 == {"cpu: POWER9 (raw), altivec supported"} and power10 != power9
    assert riscv == {"isa: rv64imafdc_zicsr", "uarch: sifive,u74-mc"}


def test_no_march_native_where_the_cpu_cannot_be_named(monkeypatch):
    """Without a CPU identity (an unread /proc/cpuinfo format), the build is generic: no -march=native code goes
    into a name another CPU could load."""
    monkeypatch.setattr(loader, "_cpu_signature", lambda: "")
    assert "-march=native" not in loader.build_flags() and "-fopenmp" in loader.build_flags()
    monkeypatch.setattr(loader, "_cpu_signature", lambda: "x86_64\nflags: avx2")
    assert "-march=native" in loader.build_flags()


@needs_cc
def test_serial_builds_and_each_compiler_get_their_own_library(cache, tmp_path, monkeypatch):
    """A compiler without OpenMP builds serially under the serial flags' name (never the OpenMP build's); two
    compilers (different ``--version``) each build their own library instead of loading the other's."""
    no_openmp = _fake_compiler(tmp_path / "cc-without-openmp",
                               f'for a in "$@"; do [ "$a" = -fopenmp ] && exit 1; done\nexec {REAL_CC} "$@"')
    other = _fake_compiler(tmp_path / "cc-other-version",
                           f'[ "$1" = --version ] && {{ echo "other 1.0"; exit 0; }}\nexec {REAL_CC} "$@"')
    for script in (no_openmp, other):
        monkeypatch.setenv("CC", str(script))
        _new_process(monkeypatch)
        assert kernels.load(KERNEL) is not None
    identity = loader.compiler_identity((str(no_openmp),))
    serial = [flag for flag in loader.build_flags() if flag != "-fopenmp"]
    assert loader._library_path(KERNEL, serial, identity).exists()
    assert not loader._library_path(KERNEL, loader.build_flags(), identity).exists()
    assert len(list(cache.glob(f"{KERNEL}-*.so"))) == 2 and len(_compiles(other)) == 1


@needs_cc
def test_an_unloadable_library_is_said_once_and_rebuilt(cache, tmp_path, monkeypatch, capsys):
    """A cached library that does not load is reported in one line, built again and loaded; the next process
    loads it silently. A compiler whose libraries never load: remembered, one line in each later process."""
    cache.mkdir(mode=0o700)
    target = _predictable_path()
    target.write_bytes(b"not a shared library")
    target.chmod(0o755)
    assert kernels.load(KERNEL) is not None
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and "did not load" in lines[0] and "building it again" in lines[0], lines
    _new_process(monkeypatch)
    assert kernels.load(KERNEL) is not None and capsys.readouterr().err == ""

    garbage = _fake_compiler(tmp_path / "garbage-cc", 'while [ "$1" != -o ]; do shift; done\necho junk > "$2"')
    monkeypatch.setenv("CC", str(garbage))
    _new_process(monkeypatch)
    assert kernels.load(KERNEL) is None and "built but did not load" in capsys.readouterr().err
    _new_process(monkeypatch)
    assert kernels.load(KERNEL) is None and len(_compiles(garbage)) == 2
    _one_notice(capsys, "built but did not load")


def _build_elsewhere(tmp_path: Path) -> bytes:
    """:data:`KERNEL` built by the system compiler with the loader's flags, outside the cache: its bytes."""
    output = tmp_path / "whole.so"
    subprocess.run([REAL_CC, *loader.build_flags(), "-I", str(loader._INCLUDE), str(loader.SOURCES[KERNEL]),
                    "-o", str(output), "-lm"], check=True)
    return output.read_bytes()


@needs_cc
def test_a_cut_short_library_is_rebuilt_not_mapped(cache, tmp_path):
    """A cached library cut short (a copy of the cache that ran out of space) was mapped as it was and the process
    ended with SIGBUS, saying nothing; it is now said in one line and built again. In a new process: nothing here
    has loaded that file."""
    cache.mkdir(mode=0o700)
    whole = _build_elsewhere(tmp_path)
    target = _predictable_path()
    target.write_bytes(whole[: len(whole) * 2 // 3])
    target.chmod(0o755)
    code = f"from svs_torch.core.kernels import load\nprint(load({KERNEL!r}) is not None, load({KERNEL!r}).{KERNEL})"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, (done.returncode, done.stderr)
    assert done.stdout.startswith("True") and "cut short" in done.stderr and "building it again" in done.stderr
    assert target.read_bytes() != whole[: len(whole) * 2 // 3]
    assert loader.cut_short(tmp_path / "whole.so") is None and loader.cut_short(target) is None
    target.write_bytes(whole[:100])
    assert "cut short" in loader.cut_short(target)


@needs_cc
def test_a_read_only_cache_that_holds_the_library_is_used(cache, tmp_path, monkeypatch, capsys):
    """A cache folder that cannot be written (a read-only home, one filled beforehand) but holds the library: it
    is loaded, without its lock file; the kernels were off ("Permission denied: '...lock'"). A kernel it lacks:
    one line that says the folder cannot be written."""
    cache.mkdir(mode=0o700)
    target = _predictable_path()
    target.write_bytes(_build_elsewhere(tmp_path))
    target.chmod(0o755)
    real_open = os.open

    def no_new_files(path, flags, *args, **kwargs):  # as root, a folder's mode does not stop us: refuse O_CREAT
        if flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", no_new_files)
    assert kernels.load(KERNEL) is not None and capsys.readouterr().err == ""
    assert kernels.load("gray_levels") is None
    _one_notice(capsys, "cannot be written", "gray_levels")
    assert not list(cache.glob("*.lock"))


def test_a_full_disk_is_not_remembered_as_a_failed_build(cache, tmp_path, monkeypatch, capsys):
    """The linker out of space was remembered as a broken compiler under its last line ("collect2: error: ld
    returned 1"): the kernels stayed off after space was freed, the serial build was tried for nothing. Now: one
    line naming the lack of space, nothing remembered, the next process compiles again."""
    script = _fake_compiler(tmp_path / "full-cc", 'echo "/usr/bin/ld: final link failed: No space left on device" >&2\n'
                                                 'echo "collect2: error: ld returned 1 exit status" >&2; exit 1')
    monkeypatch.setenv("CC", str(script))
    assert kernels.load(KERNEL) is None
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and "C kernels off" in lines[1] and "No space left on device" in lines[1], lines
    assert len(_compiles(script)) == 1 and not list(cache.glob("failed-*"))
    _new_process(monkeypatch)
    assert kernels.load(KERNEL) is None and len(_compiles(script)) == 2


def test_the_loader_lines_wait_for_the_stderr_lock(cache, monkeypatch):
    """The loader's lines are written holding STDERR_LOCK: eval's reader thread lends descriptor 2 to image
    decoders under it, and "C kernels off" written meanwhile was lost (2 runs in 3)."""
    from svs_torch.core.files import STDERR_LOCK

    held = []

    class Recorder:
        def write(self, text):
            held.append(STDERR_LOCK._is_owned())
            return len(text)

        def flush(self):
            pass

    monkeypatch.setenv("CC", str(tmp_path_missing := cache.parent / "no-such-cc"))
    monkeypatch.setattr(sys, "stderr", Recorder())
    assert kernels.load(KERNEL) is None and not tmp_path_missing.exists()
    assert held and all(held), held


def test_without_posix_owners_the_kernels_are_off_in_one_line(cache, monkeypatch, capsys):
    """Windows has no ``os.getuid``: the cache folder's check raised AttributeError, an internal error at the first
    kernel of every command. Now the folder cannot be checked, so the kernels are off, said in one line, nothing
    made."""
    monkeypatch.delattr(os, "getuid")
    assert kernels.load(KERNEL) is None
    _one_notice(capsys, "cannot be checked")
    assert not cache.exists()
