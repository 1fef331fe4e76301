"""SVS stereo camera emulator: two emulated SRV-1 boards served over TCP (and optionally pseudo-terminals).

Like the SVS's WiFi module, each board is a raw TCP server: left/master on ``--left-port`` (10001), right/slave
on ``--right-port`` (10002). One client per port at a time; a new connection replaces the old one. The
master's power-up banner goes to its first connection. With ``--pty`` each board is also served on a
pseudo-terminal whose device path is printed (open it as a serial port at any baud rate).

Run: ``python -m hw.emulator [--pty] [--images DIR] [fault options]``; Ctrl-C stops it. From Python, use
:class:`EmulatorServer` (ports 0 pick free ports; faults can be changed while it runs). The board logic is in
:mod:`hw.emulator_state`, the frame sources in :mod:`hw.frames`; this module only moves bytes.
"""

from __future__ import annotations

import errno
import json
import os
import select
import signal
import socket
import sys
import threading
import time

from .emulator_args import faults_from_args, parse_args
from .emulator_state import CameraState, Faults, Reply
from .frames import FrameSource, ImageFolderSource, ObstacleTrack, SyntheticSource
from svs_torch.data.rig_deviation import RigDeviation

__all__ = ["SVS_LINK_BYTES_PER_S", "EmulatorServer", "ListenError", "main"]

_POLL_S = 0.05  # how often the I/O threads look at the stop flag, seconds
_PREPARE_TIMEOUT_S = 600.0  # the most --prepare waits for one size's keyframes, seconds

#: The bytes a second an SVS board's link carries: its UART at 2,304,000 baud, about 2.53 Mbit/s actual, 8N1 (10
#: bits a byte), which the WiFi module bridges too (SVS_PROTOCOL.md §1). A 320×240 frame of about 14 kB takes
#: 55 ms. ``EmulatorServer(link_bytes_per_s=...)``, ``--link-rate``; the command line's ``--emulator`` uses it.
SVS_LINK_BYTES_PER_S = 253_000

_PACED_CHUNK_BYTES = 4096  # a paced reply is written in pieces this large, each when the link would have sent it
#: A paced reply's first piece: a frame's 10-byte header leaves when a board's UART would send it, not with the
#: JPEG's first 4 kB (0.36 s later at 115,200 baud), since the driver times a pair's frames by their headers.
_PACED_FIRST_BYTES = 16


class _BoardPort(threading.Thread):
    """The I/O of one board: a TCP listener with at most one client, and optionally a pty."""

    def __init__(self, state: CameraState, host: str, port: int, use_pty: bool, banner: bool,
                 send_timeout_s: float, stop: threading.Event, link_bytes_per_s: float | None = None) -> None:
        super().__init__(name=f"svs-emulator-{state.camera}", daemon=True)
        self.state = state
        self.send_timeout_s = send_timeout_s
        self.link_bytes_per_s = link_bytes_per_s
        self.stop_event = stop
        try:
            self.listener = socket.create_server((host, port))
        except OSError as err:  # said with the board and port (the option a user gives), not errno's words alone
            raise ListenError(err, state.camera, host, port) from err
        self.listener.setblocking(False)
        self.port = self.listener.getsockname()[1]
        self.client: socket.socket | None = None
        self.pending_banner = state.banner() if banner else b""
        self.drop_requested = threading.Event()
        self.pty_master: int | None = None
        self.pty_slave: int | None = None
        self.pty_path: str | None = None
        if use_pty:
            # The emulator keeps the slave end open, so the master never sees EIO when the driver closes it.
            import tty  # here, not at the top: Windows has no tty (termios), and --emulator then failed to import

            try:  # (not a ListenError: its --left-port was the wrong option to change, and the listener stayed open)
                self.pty_master, self.pty_slave = os.openpty()
                tty.setraw(self.pty_slave)
                os.set_blocking(self.pty_master, False)
                self.pty_path = os.ttyname(self.pty_slave)
            except OSError as err:
                self.close()
                raise OSError(f"--pty: the {state.camera} board cannot open a pseudo-terminal: {err}") from err

    def run(self) -> None:
        try:
            while not self.stop_event.is_set():
                self._serve_once()
        finally:
            self.close()

    def close(self) -> None:
        """Close the client, the listener and the pty (idempotent)."""
        self._close_client()
        self.listener.close()
        for fd in (self.pty_master, self.pty_slave):
            if fd is not None:
                os.close(fd)
        self.pty_master = self.pty_slave = None

    def _serve_once(self) -> None:
        if self.drop_requested.is_set():
            self.drop_requested.clear()
            self._close_client()
        readable = [self.listener] + [s for s in (self.client, self.pty_master) if s is not None]
        ready, _, _ = select.select(readable, [], [], _POLL_S)
        if self.listener in ready:
            self._accept()
        if self.client is not None and self.client in ready:
            try:
                data = self.client.recv(4096)
            except OSError:
                data = b""
            if not data:
                self._close_client()
            else:
                self._handle(data, self.client)
        if self.pty_master is not None and self.pty_master in ready:
            try:
                data = os.read(self.pty_master, 4096)
            except OSError:  # EIO: no process holds the slave end (cannot happen while we hold it)
                time.sleep(_POLL_S)
                return
            self._handle(data, self.pty_master)

    def _accept(self) -> None:
        try:
            conn, _ = self.listener.accept()
        except BlockingIOError:
            return
        self._close_client()
        conn.setblocking(True)
        conn.settimeout(self.send_timeout_s)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.client = conn
        if self.pending_banner:
            banner, self.pending_banner = self.pending_banner, b""
            self._write(conn, banner)

    def _close_client(self) -> None:
        client, self.client = self.client, None
        if client is not None:
            try:
                client.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            client.close()

    def _handle(self, data: bytes, out: socket.socket | int) -> None:
        try:
            reply = self.state.feed(data, time.monotonic())
        except Exception as err:  # noqa: BLE001 -- a frame that cannot be made: no reply, as a busy board; the
            # board serves on (its thread died before, the port closed, and the emulator looked alive).
            print(f"hw.emulator: {self.state.camera} board: no reply: {err}", file=sys.stderr, flush=True)
            return
        if reply is None:
            return
        last_write_s = self._send_reply(reply, out)
        if last_write_s is not None:
            # The hold-off runs from when the last bytes were handed to the kernel, not from when this thread
            # next runs: a client may see the reply (and answer it) before this thread is scheduled again.
            self.state.reply_sent(last_write_s)
        if reply.drop_after and last_write_s is not None and out is self.client:
            self._close_client()

    def _send_reply(self, reply: Reply, out: socket.socket | int) -> float | None:
        """Send a reply as planned; the clock reading just before its last write, or None if it was cut off.
        With ``link_bytes_per_s``, no byte leaves before the board's link would have sent it: the reply's last
        byte no earlier than its length at that rate after its first."""
        if reply.delay_s > 0 and self.stop_event.wait(reply.delay_s):
            return None
        step = max(1, reply.chunk_bytes if reply.chunk_bytes > 0 else len(reply.data))
        step = min(step, _PACED_CHUNK_BYTES) if self.link_bytes_per_s else step
        starts = list(range(0, len(reply.data), step))
        if self.link_bytes_per_s and _PACED_FIRST_BYTES < min(step, len(reply.data)):  # a frame's header first, as a
            starts.insert(1, _PACED_FIRST_BYTES)  # UART sends it: within the first chunk, no drip pause after it
        began_s = last_write_s = time.monotonic()
        for start, end in zip(starts, [*starts[1:], len(reply.data)]):
            if start % step == 0 and start and reply.chunk_delay_s > 0 and self.stop_event.wait(reply.chunk_delay_s):
                return None
            piece = reply.data[start:end]
            if self.link_bytes_per_s:
                due_s = began_s + (start + len(piece)) / self.link_bytes_per_s
                if due_s > time.monotonic() and self.stop_event.wait(due_s - time.monotonic()):
                    return None
            last_write_s = time.monotonic()
            if not self._write(out, piece):
                return None
        return last_write_s

    def _write(self, out: socket.socket | int, data: bytes) -> bool:
        """Send all of ``data``; False (and the client closed) if it cannot within ``send_timeout_s``."""
        if isinstance(out, socket.socket):
            try:
                out.sendall(data)
                return True
            except OSError:
                if out is self.client:
                    self._close_client()
                return False
        deadline = time.monotonic() + self.send_timeout_s
        view = memoryview(data)
        while view:
            _, writable, _ = select.select([], [out], [], max(0.0, deadline - time.monotonic()))
            if not writable:
                return False
            try:
                view = view[os.write(out, view):]
            except BlockingIOError:
                continue
        return True


class ListenError(OSError):
    """A board's TCP server that could not listen on ``host`` port ``port``: ``camera`` (``"left"``/``"right"``),
    and ``option``, the command line's option to change (``--host`` for an address that is not this machine's)."""

    def __init__(self, err: OSError, camera: str, host: str, port: int) -> None:
        super().__init__(err.errno, err.strerror)
        self.camera, self.port = camera, port
        # socket.create_server re-raises a name it cannot resolve as a plain OSError of getaddrinfo's negative code.
        host_wrong = isinstance(err, socket.gaierror) or (err.errno or 0) < 0 or err.errno == errno.EADDRNOTAVAIL
        self.option = "--host" if host_wrong else f"--{camera}-port"
        reason = str(err.strerror or err).split(" (while attempting")[0]
        hint = "; another program listens there (0 picks a free port)" if err.errno == errno.EADDRINUSE else ""
        self.message = f"the {camera} board cannot listen on {host} port {port}: {reason}{hint}"

    def __str__(self) -> str:
        return self.message


class EmulatorServer:
    """Two emulated boards (left = master, right = slave) served over TCP on ``host``, optionally on ptys too.

    Args:
        host: address to listen on.
        left_port, right_port: TCP ports; 0 picks free ones (see :attr:`urls`).
        source: frame source shared by both boards; default :class:`~hw.frames.SyntheticSource`.
        use_pty: also serve each board on a pseudo-terminal (see :attr:`pty_paths`).
        faults: initial faults per camera name.
        holdoff_s: input is discarded for this long after each reply, seconds (§2).
        banner: send the master's power-up banner to its first connection.
        send_timeout_s: give up sending to a client that does not read for this long, seconds.
        noise_sigma: independent Gaussian sensor noise of each board, 8-bit levels (``--noise-sigma``).
        noise_seed: seed of the left board's noise; the right board's is the next one.
        link_bytes_per_s: each board's replies paced to this many bytes a second, as its link carries them
            (:data:`SVS_LINK_BYTES_PER_S`: the SVS's UART); None: as fast as the socket takes them.
        right_deviation: the right (slave) camera mounted loosely
            (:class:`~svs_torch.data.rig_deviation.RigDeviation`, ``--right-roll-deg`` ...); None: the ideal rig.
        boards_swapped: the two boards mounted in each other's place (``--boards-swapped``): the left (master)
            board sends the right view and the right (slave) board the left one, their roles and ports as wired.
    """

    def __init__(self, host: str = "127.0.0.1", left_port: int = 10001, right_port: int = 10002, *,
                 source: FrameSource | None = None, use_pty: bool = False,
                 faults: dict[str, Faults] | None = None, holdoff_s: float = 0.001, banner: bool = True,
                 send_timeout_s: float = 2.0, noise_sigma: float = 0.0, noise_seed: int = 0,
                 link_bytes_per_s: float | None = None, right_deviation: RigDeviation | None = None,
                 boards_swapped: bool = False) -> None:
        if link_bytes_per_s is not None and not link_bytes_per_s > 0:
            raise ValueError(f"link_bytes_per_s: expected a positive rate or None, got {link_bytes_per_s!r}")
        self.source = source if source is not None else SyntheticSource()
        start = time.monotonic()
        faults = faults or {}
        self.cameras = {name: CameraState(name, role, self.source, holdoff_s=holdoff_s, start_s=start,
                                          faults=faults.get(name), noise_sigma=noise_sigma,
                                          noise_seed=noise_seed + index,
                                          deviation=right_deviation if name == "right" else None,
                                          view=("right" if name == "left" else "left") if boards_swapped else None)
                        for index, (name, role) in enumerate((("left", "master"), ("right", "slave")))}
        self._stop = threading.Event()
        self._ports: dict[str, _BoardPort] = {}
        try:
            for (name, state), port in zip(self.cameras.items(), (left_port, right_port)):
                self._ports[name] = _BoardPort(state, host, port, use_pty, banner, send_timeout_s, self._stop,
                                               link_bytes_per_s)
        except OSError:  # a port that cannot listen (ListenError), a pty not opened: none left open
            for board in self._ports.values():
                board.close()
            raise
        self.host = host
        self._started = False

    @property
    def urls(self) -> dict[str, str]:
        """``socket://`` URL of each camera, keyed ``"left"`` and ``"right"``. An IPv6 address is bracketed: the
        ``socket://::1:10001`` printed for ``--host ::1`` was refused by the driver (its port unreadable)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return {name: f"socket://{host}:{port.port}" for name, port in self._ports.items()}

    @property
    def pty_paths(self) -> dict[str, str]:
        """Pseudo-terminal device of each camera (empty without ``use_pty``)."""
        return {name: port.pty_path for name, port in self._ports.items() if port.pty_path}

    def start(self) -> EmulatorServer:
        if not self._started:
            for port in self._ports.values():
                port.start()
            self._started = True
        return self

    def stop(self) -> None:
        """Stop serving and close every socket and pty (within about a send timeout)."""
        self._stop.set()
        for port in self._ports.values():
            if port.is_alive():
                port.join(timeout=5.0)
            elif not self._started:
                port.close()
        close = getattr(self.source, "close", None)
        if close is not None:
            close()

    def set_faults(self, camera: str, **changes: object) -> None:
        """Change the faults of ``camera`` (``"left"``/``"right"``/``"both"``) while running; see :class:`Faults`."""
        for name in (("left", "right") if camera == "both" else (camera,)):
            self._camera(name).set_faults(**changes)

    def drop_connection(self, camera: str) -> None:
        """Close the current TCP client of ``camera`` (``"left"``/``"right"``/``"both"``: the WiFi module dropping,
        both ports at once) now, as a WiFi drop would. ``"both"`` was refused, though the error offered it."""
        for name in (("left", "right") if camera == "both" else (camera,)):
            self._camera(name)
            self._ports[name].drop_requested.set()

    def _camera(self, name: str) -> CameraState:
        if name not in self.cameras:
            raise ValueError(f"camera: expected 'left', 'right' (or 'both'), got {name!r}")
        return self.cameras[name]

    def __enter__(self) -> EmulatorServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _prepare_unless_stopped(source: SyntheticSource, size_wh: tuple[int, int], stop: threading.Event) -> None:
    """``--prepare``: every keyframe of ``size_wh`` rendered (at most :data:`_PREPARE_TIMEOUT_S`), unless ``stop`` is
    set first. Why: SIGTERM set ``stop`` while one wait of 600 s went on, so ``kill`` (or ``timeout``, a service
    manager) stopped nothing until every keyframe was rendered, 17 s at 1280x1024 on an idle 2-core machine."""
    deadline = time.monotonic() + _PREPARE_TIMEOUT_S
    while not stop.is_set() and time.monotonic() < deadline:
        if source.prepare(size_wh, timeout_s=_POLL_S * 5):
            return


def main(argv: list[str] | None = None) -> int:
    """Run the emulator until Ctrl-C or SIGTERM; returns the exit code."""
    args = parse_args(argv, __doc__.split("\n\n")[0], SVS_LINK_BYTES_PER_S)
    try:
        source = (ImageFolderSource(args.images, step_s=args.image_step) if args.images
                  else SyntheticSource(ObstacleTrack(floor_height_m=args.floor_height_m,
                                                     camera_pitch_deg=args.camera_pitch_deg,
                                                     heap_ahead_m=args.heap_ahead_m),
                                       renderer="simple" if args.simple_frames else "torch"))
        prepare = args.prepare_sizes
        faults = faults_from_args(args)
        chosen = ("left", "right") if args.fault_camera == "both" else (args.fault_camera,)
        server = EmulatorServer(args.host, args.left_port, args.right_port, source=source, use_pty=args.pty,
                                faults={name: faults for name in chosen}, holdoff_s=args.holdoff_ms / 1000,
                                noise_sigma=args.noise_sigma, noise_seed=args.noise_seed,
                                link_bytes_per_s=args.link_rate or None, right_deviation=args.right_deviation,
                                boards_swapped=args.boards_swapped)
    except ValueError as err:  # the image folder (no pairs, an image that does not decode)
        print(f"hw.emulator: error: {err}", file=sys.stderr)
        return 2
    except ListenError as err:  # a port in use, an address not this machine's: the option to change
        print(f"hw.emulator: error: {err.option}: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # an image folder it may not read, no pty to be had: as the system says it
        print(f"hw.emulator: error: {err}", file=sys.stderr)
        return 1
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        if isinstance(source, SyntheticSource):
            for size in prepare:
                _prepare_unless_stopped(source, size, stop)
    except KeyboardInterrupt:
        server.stop()
        return 130
    if stop.is_set():  # a SIGTERM while the keyframes rendered: nothing was served
        server.stop()
        return 0
    with server:
        if args.json:
            print(json.dumps({"urls": server.urls, "pty": server.pty_paths}), flush=True)
        else:
            for name, role in (("left", "master"), ("right", "slave")):
                pty = f"   pty {server.pty_paths[name]}" if name in server.pty_paths else ""
                print(f"{name:5s} ({role}): {server.urls[name]}{pty}", flush=True)
            print("Ctrl-C stops the emulator.", flush=True)
        try:
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
