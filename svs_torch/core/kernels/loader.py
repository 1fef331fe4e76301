"""Building, caching and loading the C kernels of :mod:`svs_torch.core.kernels`.

The shared libraries live in a private cache folder (``$SVS_TORCH_CACHE``, default ``~/.cache/svs_torch``): the
folder is created with mode 0700 and refused, with the reason in one line and the torch paths, when it belongs to
someone else or others can write to it (a library there is code run in this process); a library file that is
not ours or that others can write to is not loaded either. Each library's name hashes everything its machine code
depends on: its source, the headers the sources share, the flags it was actually built with (with OpenMP or
serially), the compiler (its resolved command and ``--version``) and the CPU (``-march=native`` code must not
reach a CPU without those instructions through a shared home folder; where the CPU cannot be named, the build
is generic). A build that fails (a compile error, a timeout, a library that does not load) is remembered in a
small ``failed-*.txt`` beside the libraries, under the same kind of key for the whole set of sources, so that
later processes neither retry nor repeat the compiler's output until a source, the flags, the compiler or the
CPU changes; the kernels are then off in the process, with one line on stderr saying why.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import hashlib
import os
import platform
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

from ..files import STDERR_LOCK, display_path, write_bytes_atomic
from .elf import cut_short

__all__ = ["FLAGS", "HEADERS", "SOURCES", "cache_dir", "open_library"]

#: The package's folder: each stage keeps its kernels in ``svs_torch/<stage>/kernels/``, this loader's folder too.
_PACKAGE = Path(__file__).resolve().parent.parent.parent
#: Each kernel's C source, named after it, in the ``kernels/`` folder of its stage.
SOURCES = {path.stem: path for path in sorted(_PACKAGE.glob("*/kernels/*.c"))}
#: The headers the sources share (``core/kernels/common.h``: thread count, scratch allocation; ``select_rank.h``:
#: the quickselect of the depth stage's statistics; depth's ``fill_row.h``: the row fill of the dense stage; features'
#: ``maxima.h``: SURF's maximum test): all part of every library's cache key (in the order of their names, as
#: before they moved beside their stages, so that the cached libraries keep their names).
HEADERS = tuple(sorted(_PACKAGE.glob("*/kernels/*.h"), key=lambda path: path.name))
#: Where ``#include "common.h"`` finds the shared header (a source's own folder is searched first).
_INCLUDE = Path(__file__).resolve().parent
#: No -ffast-math: it could assume away the +inf costs that mark disparities outside the image. -fopenmp, not threads of
#: our own: the library then needs ``libgomp.so.1``, which the torch wheel has already loaded, so the kernels' parallel
#: loops run on torch's OpenMP workers. Threads of their own had to share the two cores with those workers, which spin
#: for a while after every torch op: the Hessian kernel on 8 images took 42–66 ms with 2 pthreads, 30 ms with one, 22 ms
#: with 2 OpenMP threads. A compiler without OpenMP builds the same source serially (the pragmas are ignored), under its
#: own name. ``SVS_TORCH_CFLAGS_EXTRA`` (e.g. ``-fsanitize=address,undefined``, by ``tests/sanitize/run.sh``) appends
#: flags; being part of FLAGS they are part of every cache key, so such builds never replace the normal ones.
FLAGS = ["-O3", "-march=native", "-ffp-contract=off", "-fPIC", "-shared", "-fopenmp",
         *os.environ.get("SVS_TORCH_CFLAGS_EXTRA", "").split()]
#: ``CC --version`` answers in a few milliseconds; one that does not answer in this time is taken as hanging.
PROBE_TIMEOUT_S = 10
#: The slowest kernel (``block_match.c``) compiles in about 2 s, 7 s on two busy cores; a compile still running
#: after this is taken as hanging (and remembered: it costs one process this long once, not every kernel).
COMPILE_TIMEOUT_S = 60
#: ``/proc/cpuinfo`` keys that name the CPU's model and instruction set: x86 ``flags``, ``model name``; Arm
#: ``Features``, ``CPU part``; POWER ``cpu``; s390x ``features``, ``machine``; RISC-V ``isa``, ``uarch``.
_CPU_KEYS = frozenset({"flags", "features", "model name", "vendor_id", "cpu family", "model", "cpu implementer",
                       "cpu architecture", "cpu variant", "cpu part", "cpu", "isa", "uarch", "mvendorid", "marchid",
                       "mimpid", "machine", "platform"})
#: What a compiler says when the cache folder or ``TMPDIR`` is full: a passing state, not a failure to remember.
_NO_SPACE = (os.strerror(errno.ENOSPC), os.strerror(errno.EDQUOT), "No space left on device", "Disk quota exceeded")
#: Why the kernels are off in this process, by (cache folder, ``CC``): each said once.
_OFF: dict[tuple[str, str], str] = {}
#: The cache folders this process has announced compiling into.
_ANNOUNCED: set[str] = set()


class KernelsOff(Exception):
    """The kernels cannot run in this process; the message is the one-line reason."""


def cache_dir() -> Path:
    """Where compiled kernels live: ``$SVS_TORCH_CACHE`` or ``~/.cache/svs_torch``."""
    configured = os.environ.get("SVS_TORCH_CACHE")
    if configured:
        return Path(configured)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "svs_torch"


def _private_folder(folder: Path) -> None:
    """Create ``folder`` with mode 0700 if missing; :class:`KernelsOff` unless it (and a symlink naming it) is
    ours and only we can write to it: anyone else who can put a library there runs code in this process."""
    if not hasattr(os, "getuid"):  # Windows: no POSIX owner nor mode to check it by (it was an internal error)
        raise KernelsOff(f"cache folder {display_path(folder)}: its owner cannot be checked on this system")
    try:
        os.makedirs(folder, mode=0o700)
        os.chmod(folder, 0o700)  # the umask may have taken bits off (never adds them): the folder stays usable
    except FileExistsError:
        pass
    except OSError as error:
        raise KernelsOff(f"cache folder {display_path(folder)} cannot be made ({error.strerror}); SVS_TORCH_CACHE=DIR "
                         "names another") from None
    link, status = os.lstat(folder), os.stat(folder)
    if stat.S_ISLNK(link.st_mode) and link.st_uid not in (os.getuid(), 0):
        raise KernelsOff(f"cache folder {display_path(folder)} is a symlink owned by uid {link.st_uid}: refused")
    if not stat.S_ISDIR(status.st_mode):
        raise KernelsOff(f"cache folder {display_path(folder)} is not a folder")
    if status.st_uid != os.getuid():
        raise KernelsOff(f"cache folder {display_path(folder)} is owned by uid {status.st_uid}, not by this user "
                         f"(uid {os.getuid()}): refused")
    if status.st_mode & 0o022:
        raise KernelsOff(f"cache folder {display_path(folder)} is writable by group or others (mode "
                         f"{stat.S_IMODE(status.st_mode):o}): refused")


def _untrusted(library: Path) -> str | None:
    """Why the library file must not be loaded (not a plain file, not ours, writable by others), or None."""
    status = os.lstat(library)
    if not stat.S_ISREG(status.st_mode):
        return f"{display_path(library)} is not a plain file: not loaded"
    if status.st_uid != os.getuid():
        return f"{display_path(library)} is owned by uid {status.st_uid}: not loaded"
    if status.st_mode & 0o022:
        return f"{display_path(library)} is writable by others (mode {stat.S_IMODE(status.st_mode):o}): not loaded"
    return None


@functools.cache
def _cpu_signature() -> str:
    """``platform.machine()`` and the lines that name the CPU's model and instruction set, or "" where none can
    be read (then the kernels are built without ``-march=native``)."""
    try:
        lines = _cpu_lines(Path("/proc/cpuinfo").read_text(errors="replace"))
    except OSError:
        lines = set()
    if not lines and sys.platform == "darwin":
        for key in ("machdep.cpu.brand_string", "machdep.cpu.features"):
            done = _run(["sysctl", "-n", key], PROBE_TIMEOUT_S, check=False)
            if done is not None and done.returncode == 0 and done.stdout.strip():
                lines.add(f"{key}: {done.stdout.decode(errors='replace').strip()}")
    return "\n".join([platform.machine(), *sorted(lines)]) if lines else ""


def _cpu_lines(cpuinfo: str) -> set[str]:
    """The lines of a ``/proc/cpuinfo`` text that name the CPU's model and instruction set (:data:`_CPU_KEYS`)."""
    lines = set()
    for line in cpuinfo.splitlines():
        key, colon, value = line.partition(":")
        if colon and key.strip().lower() in _CPU_KEYS:
            lines.add(f"{key.strip().lower()}: {value.strip()}")
    return lines


def build_flags() -> list[str]:
    """:data:`FLAGS`, less ``-march=native`` where the CPU cannot be named (its code would go into a name that
    another CPU sharing the cache could load)."""
    return FLAGS if _cpu_signature() else [flag for flag in FLAGS if flag != "-march=native"]


def _run(argv: list[str], timeout_s: float, check: bool = True) -> subprocess.CompletedProcess | None:
    """``argv``'s result, or None if it could not start; past ``timeout_s`` its whole process group is killed
    (a compiler driver's children would otherwise hold the pipes open, and ``subprocess.run`` wait on them) and,
    with ``check``, :class:`KernelsOff` raised."""
    try:
        process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   start_new_session=True)
    except OSError:
        return None
    with process:
        try:
            stdout, stderr = process.communicate(timeout=timeout_s)
        except BaseException as error:  # past the timeout, or Ctrl-C / SIGTERM (its own session: none reaches it)
            try:
                os.killpg(process.pid, signal.SIGKILL)
            except (AttributeError, OSError):  # no process groups here, or the group is gone: the child alone
                process.kill()
            process.communicate()
            if not isinstance(error, subprocess.TimeoutExpired):  # the caller's finally removes the half-built file
                raise
            if check:
                shown = shlex.join(argv[:3]) + ("…" if len(argv) > 3 else "")
                raise KernelsOff(f"{shown} did not finish within {timeout_s:g} s") from None
            return None
    return subprocess.CompletedProcess(argv, process.returncode, stdout, stderr)


def compiler_command() -> list[str]:
    """``$CC`` split as a shell would (``"ccache gcc"``), or the first of ``cc``, ``gcc``, ``clang`` found;
    its program resolved to a path. :class:`KernelsOff` when there is none."""
    configured = os.environ.get("CC", "").strip()
    try:
        argv = shlex.split(configured) if configured else [next(
            (name for name in ("cc", "gcc", "clang") if shutil.which(name)), "cc")]
    except ValueError as error:
        raise KernelsOff(f"CC={configured!r} cannot be split ({error})") from None
    program = shutil.which(argv[0])
    if program is None:
        raise KernelsOff(f"{argv[0]}: not found" + (f" (CC={configured!r})" if configured else ""))
    return [program, *argv[1:]]


@functools.cache
def compiler_identity(command: tuple[str, ...]) -> str:
    """What names the compiler ``command`` in the cache key: the command, its program's real path, size and modification
    time, and its ``--version``, asked once per process at its first kernel (gcc answers a bare Python in 3 ms, one with
    torch loaded in 10–23 ms: the cost of starting a process from it). :class:`KernelsOff` when the probe hangs."""
    program = os.stat(command[0])
    done = _run([*command, "--version"], PROBE_TIMEOUT_S)
    version = done.stdout.decode(errors="replace") if done is not None and done.returncode == 0 else "(no --version)"
    return "\n".join([shlex.join(command), os.path.realpath(command[0]), str(program.st_size),
                      str(program.st_mtime_ns), version])


def _digest(*parts: str | bytes) -> str:
    digest = hashlib.sha256()
    for part in parts:
        digest.update(part.encode() if isinstance(part, str) else part)
        digest.update(b"\0")
    return digest.hexdigest()[:16]


def _library_path(name: str, flags: list[str] | None = None, compiler: str = "") -> Path:
    """The library of kernel ``name`` built with ``flags`` (default :func:`build_flags`) by the compiler of
    identity ``compiler``: its name hashes the source, the headers, the flags, the compiler and the CPU."""
    source = SOURCES[name]
    return cache_dir() / (f"{name}-" + _digest(source.read_bytes(), *(header.read_bytes() for header in HEADERS),
                                               shlex.join(flags or build_flags()), compiler, _cpu_signature(),
                                               platform.machine()) + ".so")


@functools.cache
def _sources_digest() -> str:
    """All the kernels' sources and headers, hashed once per process."""
    return _digest(*(path.read_bytes() for path in sorted([*SOURCES.values(), *HEADERS], key=lambda p: p.name)))


def _failure_marker(flags: list[str], compiler: str) -> Path:
    """Where a failed build with ``flags`` by ``compiler`` is remembered: one file for the whole set of sources
    (one kernel failing turns them all off), named by the same things as the libraries."""
    return cache_dir() / f"failed-{_digest(_sources_digest(), shlex.join(flags), compiler, _cpu_signature())}.txt"


def _first_line(marker: Path) -> str:
    """The reason a marker records (its first line) and how to retry."""
    lines = marker.read_text(errors="replace").splitlines()
    return f"{lines[0] if lines else 'an earlier build failed'}; remembered in {display_path(marker)} (remove to retry)"


def _trusted_library(library: Path) -> ctypes.CDLL:
    """``library`` loaded, :class:`KernelsOff` if it is not ours alone (OSError if it does not load or is cut short)."""
    reason = _untrusted(library)
    if reason is not None:
        raise KernelsOff(reason)
    short = cut_short(library)
    if short is not None:
        raise OSError(f"{display_path(library)}: {short}")
    return ctypes.CDLL(str(library))


def _say(line: str) -> None:
    """One line on stderr, under STDERR_LOCK: ``eval``'s decoder thread lends descriptor 2 under it (a line lost)."""
    with STDERR_LOCK:
        print(line, file=sys.stderr, flush=True)


class _BuildFailed(Exception):
    """A kernel did not build or load: the message's first line is the reason, the rest the compiler's output;
    ``hung``: the compiler did not finish (no other flags are tried)."""

    def __init__(self, message: str, hung: bool = False):
        super().__init__(message)
        self.hung = hung


def _announce(folder: Path) -> None:
    """One line per process and cache folder, before its first compile."""
    if str(folder) not in _ANNOUNCED:
        _ANNOUNCED.add(str(folder))
        _say(f"svs_torch: compiling the C kernels for this machine into {display_path(folder)} as they are first "
             "needed (once, a few seconds each; later runs reuse them)")


def _compile(name: str, command: list[str], flags: list[str], target: Path) -> None:
    """Build kernel ``name`` into ``target``, or raise :class:`_BuildFailed`."""
    _announce(target.parent)
    # Built under a temporary name and renamed: a concurrent process never loads a half-written library.
    handle, temporary = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(handle)
    argv = [*command, *flags, "-I", str(_INCLUDE), str(SOURCES[name]), "-o", temporary, "-lm"]
    try:
        try:
            done = _run(argv, COMPILE_TIMEOUT_S)
        except KernelsOff:
            raise _BuildFailed(f"compiling the {name} kernel did not finish within {COMPILE_TIMEOUT_S} s "
                               f"({shlex.join(command)})", hung=True) from None
        if done is None:
            raise _BuildFailed(f"{shlex.join(command)} could not be started")
        if done.returncode != 0:
            output = done.stderr.decode(errors="replace").strip().splitlines()
            full = next((line.strip() for line in output if any(text in line for text in _NO_SPACE)), None)
            if full is not None:  # not the compiler's fault: not remembered (it turned the kernels off for good)
                raise KernelsOff(f"compiling the {name} kernel ran out of disk space ({full}); the next run tries "
                                 "again")
            first = next((line for line in output if "error" in line), output[0] if output else "")
            reason = first or f"exit status {done.returncode}"
            raise _BuildFailed("\n".join([f"the {name} kernel did not compile with {shlex.join(command)}: {reason}",
                                          shlex.join(argv), *output[:20]]))
        os.chmod(temporary, 0o755)  # the linker's mode follows the umask: never writable by others
        os.replace(temporary, target)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def _built(name: str, command: list[str], flags: list[str], target: Path) -> ctypes.CDLL:
    """The library at ``target``, built first if missing; a cached one that does not load is said once, removed
    and built again. Under a lock file, so that processes started together (``svs-depth estimate``'s workers)
    build a kernel once and the others wait for it."""
    try:
        import fcntl
    except ImportError:  # not POSIX: concurrent builds stay correct (atomic rename), only repeated
        fcntl = None
    try:
        handle = os.open(target.with_suffix(".lock"), os.O_WRONLY | os.O_CREAT, 0o600)
    except OSError as error:  # a read-only cache: a library there is whole (renamed in complete), loaded as it is
        if not target.exists():  # (the missing lock turned the kernels off though every library was there)
            raise KernelsOff(f"cache folder {display_path(target.parent)} cannot be written ({error.strerror}) "
                             f"and holds no {name} kernel; SVS_TORCH_CACHE=DIR names another") from None
        return _trusted_library(target)
    try:
        if fcntl is not None:
            fcntl.flock(handle, fcntl.LOCK_EX)
        fresh = not target.exists()
        if fresh:
            _compile(name, command, flags, target)
        try:
            return _trusted_library(target)
        except OSError as error:
            if fresh:
                raise _BuildFailed(f"the {name} kernel built but did not load ({error})") from None
            _say(f"svs_torch: the cached {display_path(target)} did not load ({error}); building it again")
        target.unlink()
        _compile(name, command, flags, target)
        try:
            return _trusted_library(target)
        except OSError as error:
            raise _BuildFailed(f"the {name} kernel built but did not load ({error})") from None
    finally:
        os.close(handle)


def _remember(marker: Path, failure: str, flags: list[str], compiler: str) -> None:
    """Write the failure marker: its reason, the key it holds for, and the compiler's first lines."""
    reason, _, details = failure.partition("\n")
    write_bytes_atomic(marker, "\n".join([reason, f"flags: {shlex.join(flags)}", f"sources: {_sources_digest()}",
                                          f"compiler: {compiler}", f"cpu: {_cpu_signature()}", details, ""]).encode())


def _open(name: str) -> ctypes.CDLL:
    """The library of kernel ``name``, or :class:`KernelsOff`."""
    folder = cache_dir()
    _private_folder(folder)
    command = compiler_command()
    program = os.stat(command[0])
    probe_marker = folder / f"failed-{_digest(shlex.join(command), str(program.st_size), str(program.st_mtime_ns))}.txt"
    if probe_marker.exists():
        raise KernelsOff(_first_line(probe_marker))
    try:
        compiler = compiler_identity(tuple(command))
    except KernelsOff as hung:
        _remember(probe_marker, str(hung), [], shlex.join(command))
        raise KernelsOff(_first_line(probe_marker)) from None
    openmp = build_flags()
    variants = [openmp, [flag for flag in openmp if flag != "-fopenmp"]]  # the serial build: a compiler without OpenMP
    for index, flags in enumerate(variants):
        marker = _failure_marker(flags, compiler)
        if marker.exists():
            continue
        try:
            return _built(name, command, flags, _library_path(name, flags, compiler))
        except _BuildFailed as failure:
            # A hanging compiler is not tried again with other flags, in this process or a later one.
            for later in variants[index:index + 1] if not failure.hung else variants[index:]:
                if not _failure_marker(later, compiler).exists():  # another process may have recorded it
                    _remember(_failure_marker(later, compiler), str(failure), later, compiler)
    raise KernelsOff(_first_line(_failure_marker(variants[-1], compiler)))


def open_library(name: str) -> ctypes.CDLL | None:
    """The compiled kernel ``name`` (``svs_torch/<stage>/kernels/{name}.c``), built on first use; None when the kernels
    are off in this process (the cache folder refused, no working compiler, a failed build), said once on stderr
    in one line."""
    state = (str(cache_dir()), os.environ.get("CC", ""))
    if state in _OFF:
        return None
    try:
        return _open(name)
    except (KernelsOff, OSError) as reason:
        _OFF[state] = str(reason)
        _say(f"svs_torch: C kernels off ({reason}); running the torch paths (slower). Set SVS_TORCH_KERNELS=torch "
             "to silence.")
        return None
