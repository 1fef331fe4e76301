"""The child processes of ``svs-depth bench``, run so that an interrupted benchmark leaves none of theirs behind.

Why: a rival is a process with children of its own (the OpenCV pool's spawned workers and their resource
tracker; ``svs-depth estimate``'s worker server and workers). ``subprocess.run`` ends only the direct child when
the benchmark is interrupted, so a SIGINT sent to the benchmark alone (``timeout -s INT``, a job runner,
``kill -INT PID``), or a SIGTERM, left the pool's workers running as orphans after ``svs-depth bench`` had said
"interrupted" and exited 130 (an audit). Each child now runs in a process group of its own; on any exception
(KeyboardInterrupt, Terminated) the whole group is sent SIGINT, as a terminal's Ctrl-C would, so that each
process cleans up after itself, and SIGKILL after :data:`GRACE_S` seconds for what is still there.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time

__all__ = ["GRACE_S", "run_child"]

#: Seconds an interrupted child's process group has to end on SIGINT before it is killed.
GRACE_S = 5.0


def run_child(command: list[str], env: dict[str, str] | None = None, check: bool = False
              ) -> subprocess.CompletedProcess:
    """``subprocess.run(command, capture_output=True, text=True, env=env, check=check)``, the child in a process
    group of its own where the platform has them (POSIX), and that group ended whenever the wait is interrupted."""
    if os.name != "posix":
        return subprocess.run(command, capture_output=True, text=True, env=env, check=check)
    # A session of its own (Python 3.10 has no process_group=): its group's id is its pid.
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                               start_new_session=True)
    try:
        out, err = process.communicate()
    except BaseException:
        _end_group(process)
        raise
    if check and process.returncode:
        raise subprocess.CalledProcessError(process.returncode, command, out, err)
    return subprocess.CompletedProcess(command, process.returncode, out, err)


def _end_group(process: subprocess.Popen) -> None:
    """SIGINT to ``process``'s group, SIGKILL to what is left of it after :data:`GRACE_S`; ``process`` reaped."""
    group = process.pid
    try:
        os.killpg(group, signal.SIGINT)
    except ProcessLookupError:
        pass
    deadline = time.monotonic() + GRACE_S
    while time.monotonic() < deadline and _group_alive(group):
        process.poll()  # reaps the direct child; its own children are reaped by their parents or by init
        time.sleep(0.05)
    try:
        os.killpg(group, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.kill()  # (a no-op once it has ended)
    process.communicate()


def _group_alive(group: int) -> bool:
    """Whether a process of ``group`` still runs (not counting zombies, which take no more work)."""
    try:
        names = os.listdir("/proc")
    except OSError:  # no /proc (macOS): ask the group itself, zombies included
        try:
            os.killpg(group, 0)
        except ProcessLookupError:
            return False
        return True
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", encoding="ascii", errors="replace") as handle:
                fields = handle.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == group and fields[0] != "Z":
            return True
    return False
