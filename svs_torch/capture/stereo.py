"""The SVS stereo camera: two SRV-1 links (left = master, right = slave), grabbed as approximately simultaneous pairs.

The two boards are not hardware-synchronised (``SVS_PROTOCOL.md`` §1): :meth:`SVSStereoCamera.grab_pair` sends
``I`` on both links back to back, reads both replies concurrently, and timestamps each frame when its header and
its last byte arrive; :attr:`StereoPair.time_between_frames_s` says how far apart the two boards' replies began
(:mod:`.stereo_frames`).
"""

from __future__ import annotations

import collections
import queue
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from typing import TypeVar

import numpy as np
import torch

from ..core.camera import SVS_CAMERA, SVSCamera
from ..core.checks import InputError
from ..core.daemon_task import DaemonTask
from ..core.types import StereoBatch
from .link import CameraLink, check_link_url
from .link_types import CaptureError, DamagedFrameError, LinkConfig
from .protocol import VersionInfo, size_code_for
from .stereo_frames import Frame, PairBatch, StereoPair, decode_frame, time_between_frames_s

__all__ = ["STEREO_ROLES", "Frame", "StereoPair", "PairBatch", "SVSStereoCamera", "to_stereo_batch", "decode_frame"]

#: Each board's role in a stereo build (its version line): the master is the left camera (port 10001).
STEREO_ROLES = {"left": "master", "right": "slave"}

T = TypeVar("T")
_CONNECT_TIMEOUT_S = 5.0  # pyserial's fixed socket:// connect timeout


def to_stereo_batch(pairs: list[StereoPair] | tuple[StereoPair, ...], *, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None, camera: SVSCamera = SVS_CAMERA) -> StereoBatch:
    """Stack pairs into a :class:`StereoBatch`: grayscale in [0, 1] ``(B, 1, H, W)``, nominal SVS calibration.

    ``focal_px = camera.focal_px(W)``, ``baseline_m = camera.baseline_m``, ``calibrated`` False (nominal values),
    names ``pair<index>``. All pairs must have one size.
    """
    if not pairs:
        raise InputError("pairs: expected at least one stereo pair, got none")
    sizes = {frame.size_wh for pair in pairs for frame in (pair.left, pair.right)}
    if len(sizes) != 1:
        raise InputError(f"pairs: expected one frame size, got {sorted(sizes)}")
    width = sizes.pop()[0]

    def stack(frames: list[Frame]) -> torch.Tensor:
        images = torch.from_numpy(np.stack([f.image for f in frames]))[:, None]  # (B, 1, H, W) uint8
        return images.to(device=device, dtype=dtype) / 255.0

    return StereoBatch.from_images(stack([p.left for p in pairs]), stack([p.right for p in pairs]),
                                   focal_px=camera.focal_px(width), baseline_m=camera.baseline_m,
                                   calibrated=False, names=tuple(f"pair{p.index}" for p in pairs))


#: The most two frames of one pair may arrive apart before both are grabbed again (:class:`SVSStereoCamera`): both
#: boards' frames arrive within a few tens of milliseconds, and a retry of one board's grab waits its reply timeout.
MAX_FRAME_GAP_S = 0.25
#: How many times a pair whose frames came too far apart is grabbed again.
REGRABS_FOR_GAP = 2
#: How many times a pair with a frame damaged on the link (:class:`DamagedFrameError`) is grabbed again before the
#: damage is reported as the camera's failure: one damaged frame is a link's bit error, three in a row a link that
#: cannot carry frames.
REGRABS_FOR_DAMAGE = 2


class SVSStereoCamera:
    """Both SVS boards: open, identify (``V``), set size, grab pairs; a context manager that closes the links.

    Args:
        left_url, right_url: pyserial URLs of the left (master, TCP 10001) and right (slave, TCP 10002) boards,
            e.g. ``socket://192.168.0.15:10001`` or ``/dev/ttyUSB0``.
        size_wh: frame size (width, height) in pixels: 160x120, 320x240, 640x480 or 1280x1024.
        quality: JPEG quality digit 1 (best) … 8 (worst); None leaves the board's setting (default 4).
        flip: True sends ``y`` (camera mounted upside down), False ``Y``, None nothing.
        config: timeouts and UART settings of both links.
        strict_roles: raise instead of warn when the left board is not the master or the right not the slave.
        first_index: the index of the first pair grabbed (a camera opened again after a loss goes on counting, so
            a record's pair files are not overwritten).
        max_frame_gap_s: a pair whose two frames arrived further apart (one board needed a retry while the other's
            frame waited) is grabbed again, both boards, up to twice; None: never. A walker moves and the scene
            with him: frames seconds apart are not a stereo pair.

    Raises:
        InputError: a bad ``size_wh`` or ``quality``.
        CaptureError: a link cannot be opened or does not answer; the message names the camera and URL.
    """

    def __init__(self, left_url: str, right_url: str, size_wh: tuple[int, int] = (320, 240), *,
                 quality: int | None = None, flip: bool | None = None, config: LinkConfig | None = None,
                 strict_roles: bool = False, first_index: int = 0, max_frame_gap_s: float | None = MAX_FRAME_GAP_S
                 ) -> None:
        self._size_code = size_code_for(size_wh)
        check_link_url(left_url, "left_url")
        check_link_url(right_url, "right_url")
        if max_frame_gap_s is not None and not (isinstance(max_frame_gap_s, (int, float)) and max_frame_gap_s > 0):
            raise InputError(f"max_frame_gap_s: expected seconds > 0 or None, got {max_frame_gap_s!r}")
        self.max_frame_gap_s = max_frame_gap_s
        if isinstance(first_index, bool) or not isinstance(first_index, int) or first_index < 0:
            raise InputError(f"first_index: expected an integer >= 0, got {first_index!r}")
        if quality is not None and (not isinstance(quality, int) or not 1 <= quality <= 8):
            raise InputError(f"quality: expected an integer 1 (best) to 8 (worst) or None, got {quality!r}")
        self.links = {"left": CameraLink(left_url, "left", config), "right": CameraLink(right_url, "right", config)}
        self.size_wh = tuple(size_wh)
        self.versions: dict[str, VersionInfo] = {}
        self._closed = False
        self._next_index = first_index
        try:
            self._both(lambda link: self._setup(link, quality, flip), wait_at_exit=False)
            self._check_roles(strict_roles)
        except BaseException:
            self.close()
            raise

    def _setup(self, link: CameraLink, quality: int | None, flip: bool | None) -> None:
        link.open()
        self.versions[link.name] = link.identify()
        link.configure(self._size_code, quality, flip)

    @property
    def roles_swapped(self) -> bool | None:
        """Whether the boards answered ``V`` in the wrong roles, the left not the stereo master or the right not the
        slave (the URLs likely given the other way round); None where a board's build names no role. capture marks
        each pair so (``cameras_swapped`` in its index) and guide says it aloud (it warned once as it started, then
        saved every pair unmarked: an audit of a rig set up with the emulator's ports the other way round)."""
        roles = {name: self.versions[name].role for name in STEREO_ROLES}
        if not set(roles.values()) <= set(STEREO_ROLES.values()):
            return None
        return roles != STEREO_ROLES

    def _check_roles(self, strict: bool) -> None:
        roles = {name: self.versions[name].role for name in STEREO_ROLES}
        if roles == STEREO_ROLES:
            return
        over_wifi = all(link.url.startswith("socket://") for link in self.links.values())
        where = "port 10001 is the master" if over_wifi else "the master's serial device is the left camera's"
        message = (f"left/right: expected the left board ({self.links['left'].url}) to be the stereo master and the "
                   f"right ({self.links['right'].url}) the slave, got left {roles['left']}, right {roles['right']}; "
                   f"check the URLs ({where}) and cover one lens to confirm")
        if strict:
            raise CaptureError(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)

    @property
    def config(self) -> LinkConfig:
        return self.links["left"].config

    def pair_timeout_s(self) -> float:
        """Worst-case seconds of :meth:`grab_pair` when every retry and reconnect is used (pessimistic bound; a pair
        grabbed again for its frames' gap, ``max_frame_gap_s``, pays its frames' time again)."""
        cfg = self.config
        frame = (cfg.max_retries + 1) * cfg.frame_attempt_timeout_s(self._size_code)
        reconnect = cfg.max_reconnects * (cfg.max_reconnects + 1) * (cfg.reconnect_delay_s + _CONNECT_TIMEOUT_S
                                                                      + cfg.drain_max_s + cfg.reply_timeout_s)
        regrabs = REGRABS_FOR_DAMAGE + (0 if self.max_frame_gap_s is None else REGRABS_FOR_GAP)
        return (1 + regrabs) * frame + reconnect

    def set_size(self, size_wh: tuple[int, int]) -> None:
        """Change the frame size on both boards."""
        code = size_code_for(size_wh)
        self._both(lambda link: link.set_size(code), wait_at_exit=False)
        self._size_code, self.size_wh = code, tuple(size_wh)

    @property
    def next_index(self) -> int:
        """The index the next pair grabbed will have (the first camera's count, for one opened again)."""
        return self._next_index

    def grab_pair(self) -> StereoPair:
        """Send ``I`` to both boards back to back, read both frames concurrently, decode them to grayscale.

        A pair with a frame damaged on the link (:class:`DamagedFrameError`) is grabbed again, both boards, up to
        :data:`REGRABS_FOR_DAMAGE` times.

        Raises:
            CaptureError: a camera gave no valid frame within its retries (the message names it);
                :class:`DamagedFrameError` when its frames were damaged every time.
        """
        gap_regrabs = damage_regrabs = 0
        while True:
            self.links["left"].request_frame()
            self.links["right"].request_frame()
            try:
                left, right = self._both(lambda link: decode_frame(link.read_frame(), link.name, link.where))
            except DamagedFrameError:
                if damage_regrabs == REGRABS_FOR_DAMAGE:
                    raise
                damage_regrabs += 1  # both boards again: a pair is two frames of one moment
                continue
            _check_pair_size(left, right, self.size_wh)
            gap_s = time_between_frames_s(left, right)
            if self.max_frame_gap_s is None or abs(gap_s) <= self.max_frame_gap_s or gap_regrabs == REGRABS_FOR_GAP:
                break
            gap_regrabs += 1
        pair = StereoPair(index=self._next_index, left=left, right=right, time_between_frames_s=gap_s)
        self._next_index += 1
        return pair

    def grab_pairs(self, count: int) -> list[StereoPair]:
        """``count`` pairs, one after the other."""
        return [self.grab_pair() for _ in range(count)]

    def stream_batches(self, batch_size: int, *, num_batches: int | None = None, dtype: torch.dtype = torch.float32,
                       device: torch.device | str | None = None, idle_s: float | None = None
                       ) -> Iterator[PairBatch | None]:
        """Grab pairs continuously in a background thread; yield each time ``batch_size`` new pairs arrived.

        Each item holds the ``batch_size`` most recent pairs; pairs that arrived while the consumer was busy and
        are no longer among them are counted in ``num_dropped`` (at most ``batch_size`` pairs wait untaken: a
        consumer kept busy, such as guide whose stdout stalled, does not fill the memory). Stops after
        ``num_batches`` (None: never) or when the generator is closed; a capture error in the background is raised
        here (and no batch within ``batch_size`` times :meth:`pair_timeout_s`). With ``idle_s``, None is yielded
        each ``idle_s`` seconds no batch came in the meantime: the consumer can act on the wait (``guide`` says it
        cannot see when the link froze while the driver retried, instead of seconds of silence). Do not call
        :meth:`grab_pair` while streaming.
        """
        if not isinstance(batch_size, int) or batch_size < 1:
            raise InputError(f"batch_size: expected a positive integer, got {batch_size!r}")
        if idle_s is not None and not (isinstance(idle_s, (int, float)) and idle_s > 0):
            raise InputError(f"idle_s: expected None or a positive number of seconds, got {idle_s!r}")
        state = _Stream(batch_size)
        thread = threading.Thread(target=self._stream_loop, args=(state,), name="svs-stream", daemon=True)
        thread.start()
        try:
            produced = 0
            timeout_s = batch_size * self.pair_timeout_s()
            while num_batches is None or produced < num_batches:
                deadline = time.monotonic() + timeout_s
                taken = None
                while taken is None:
                    left_s = deadline - time.monotonic()
                    if left_s <= 0:
                        raise CaptureError(f"stream_batches: no {batch_size} new pairs within {timeout_s:.1f} s")
                    taken = state.take(left_s if idle_s is None else min(idle_s, left_s))
                    if taken is None and idle_s is not None:
                        yield None
                pairs, dropped = taken
                yield PairBatch(to_stereo_batch(pairs, dtype=dtype, device=device), pairs, dropped)
                produced += 1
        finally:
            state.stopped = True
            thread.join(timeout=self.pair_timeout_s())

    def _stream_loop(self, state: _Stream) -> None:
        try:
            while not state.stopped:
                state.put(self.grab_pair())
        except Exception as err:  # handed to the consumer, which raises it
            state.arrived.put(err)

    def close(self) -> None:
        """Close both links (concurrently: pyserial's socket close sleeps 0.3 s each); safe to call twice (a close
        that a Ctrl-C cut short closes what is left when called again)."""
        self._closed = True
        for task in [DaemonTask(link.close, name=f"svs-close-{link.name}", wait_at_exit=False)
                     for link in self.links.values()]:
            task.result()

    def _both(self, work: Callable[[CameraLink], T], wait_at_exit: bool = True) -> tuple[T, T]:
        """Run ``work`` on the left and right links concurrently, each in a daemon thread (not a pool: a Ctrl-C must
        never wait on a board; ``core.daemon_task`` says why); re-raise a failure after both finished. The exit
        waits only for a decoding ``work`` (OpenCV): a Ctrl-C as an unreachable board was opened waited 4.1 s."""
        if self._closed:
            raise CaptureError("SVSStereoCamera: the camera is closed")
        tasks = [DaemonTask(work, self.links[n], name=f"svs-{n}", wait_at_exit=wait_at_exit) for n in STEREO_ROLES]
        errors = [task.exception() for task in tasks]
        failed = [e for e in errors if e is not None]
        if len(failed) == 2 and all(isinstance(e, CaptureError) for e in failed):
            both_damaged = all(isinstance(e, DamagedFrameError) for e in failed)
            raise (DamagedFrameError if both_damaged else CaptureError)(f"{failed[0]}; and {failed[1]}") from failed[0]
        for name, error in zip(STEREO_ROLES, errors):
            if isinstance(error, CaptureError):
                error.camera = name  # (guide says which camera is lost)
        if failed:
            raise failed[0]
        return tasks[0].result(), tasks[1].result()

    def __enter__(self) -> SVSStereoCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _check_pair_size(left: Frame, right: Frame, size_wh: tuple[int, int]) -> None:
    """CaptureError unless both frames are at the camera's ``size_wh``. Why: a :meth:`SVSStereoCamera.set_size` that
    one board refused left the other at the new size, and each link checks only its own: the pairs grabbed after it
    joined a 640x480 left frame with a 320x240 right one, and capture's index gave the left one's size for both."""
    if left.size_wh == right.size_wh == tuple(size_wh):
        return
    raise CaptureError(f"left/right: expected both frames at {size_wh[0]}x{size_wh[1]}, got left "
                       f"{left.size_wh[0]}x{left.size_wh[1]}, right {right.size_wh[0]}x{right.size_wh[1]} (a size "
                       "change one board refused: set the size again)")


class _Stream:
    """What :meth:`SVSStereoCamera.stream_batches` shares with its grabbing thread: a C queue of pairs (or the
    thread's error), and a stop flag. No Condition or Event: a Ctrl-C that landed as the consumer took one's lock
    left it held, and the grabbing thread waited on it for good while the consumer waited for that thread (guide
    hung after Ctrl-C at 4 places of 16, an audit that interrupted each place in turn: tests/cli/test_interrupts)."""

    def __init__(self, batch_size: int) -> None:
        self.recent: collections.deque[StereoPair] = collections.deque(maxlen=batch_size)
        self.batch_size = batch_size
        self.new = 0  # pairs taken off the queue since the last batch (the consumer's alone)
        self.arrived: queue.SimpleQueue[StereoPair | BaseException] = queue.SimpleQueue()  # (or the error)
        self.stopped = False
        self.discarded = 0  # pairs the grabbing thread took off the queue untaken (:meth:`put`; that thread's alone)
        self.discarded_seen = 0  # of them, those counted dropped in a batch (the consumer's alone)

    def put(self, pair: StereoPair) -> None:
        """The grabbing thread's: queue ``pair``, and take the oldest off while more than ``batch_size`` wait (counted
        dropped at the next batch). Why: a consumer that took none kept every pair grabbed meanwhile: ``guide
        --json`` whose reader stalled (its write blocked) grew by 3.2 MB a second, without bound (an audit of long
        runs). The queue holds pairs alone until the thread's error, its last item."""
        self.arrived.put(pair)
        while self.arrived.qsize() > self.batch_size:
            try:
                self.arrived.get_nowait()
            except queue.Empty:  # the consumer took them meanwhile
                return
            self.discarded += 1

    def take(self, timeout_s: float) -> tuple[tuple[StereoPair, ...], int] | None:
        """The latest pairs and how many were dropped, once ``batch_size`` new ones came; None after ``timeout_s``
        without them; the grabbing thread's error raised."""
        deadline = time.monotonic() + timeout_s
        while True:
            waiting = self.new < self.batch_size
            try:
                item = (self.arrived.get(timeout=max(0.0, deadline - time.monotonic())) if waiting
                        else self.arrived.get_nowait())
            except queue.Empty:
                if waiting:
                    return None
                discarded = self.discarded  # (read once: the grabbing thread may add one meanwhile)
                dropped = self.new - self.batch_size + discarded - self.discarded_seen
                self.new, self.discarded_seen = 0, discarded
                return tuple(self.recent), dropped
            if isinstance(item, BaseException):
                raise item
            self.recent.append(item)
            self.new += 1
