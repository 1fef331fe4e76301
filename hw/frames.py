"""Frame sources for the SVS emulator: synthetic obstacles at known depths, or a folder of stereo images.

A frame source is a callable ``source(camera, width, height, time_s) -> (H, W) uint8 grayscale`` where
``camera`` is ``"left"`` or ``"right"`` and ``time_s`` the emulator's clock in seconds. Sources are shared by
both emulated boards (which run in different threads), so they are thread-safe, and they never block a reply
for long: the synthetic source renders in a background thread and serves a cheap stand-in until it is done.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from svs_torch.core.camera import SVS_CAMERA, SVSCamera
from svs_torch.data.synthetic import WALL_DEPTH_M

__all__ = ["FrameSource", "MIN_IMAGE_STEP_S", "ObstacleTrack", "SyntheticSource", "ImageFolderSource",
           "render_simple_pair"]

FrameSource = Callable[[str, int, int, float], np.ndarray]

#: A walker's cameras over a floor (``ObstacleTrack.floor_height_m``), pitched down this many degrees unless told.
WALKER_PITCH_DEG = 20.0
#: The most :meth:`SyntheticSource.close` waits for the keyframe being rendered, seconds.
RENDER_STOP_TIMEOUT_S = 120.0
#: How often SyntheticSource.prepare looks whether the keyframes it waits for are rendered.
PREPARE_POLL_S = 0.02
#: The shortest time an image folder's pair is shown (:class:`ImageFolderSource`), seconds: shorter, each grab shows
#: another pair all the same. Why: 5e-324 was taken as "positive", and the clock over it overflowed at every grab
#: ("cannot convert float infinity to integer"), so neither board ever sent a frame.
MIN_IMAGE_STEP_S = 1e-6

_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff"}


class ObstacleTrack:
    """Obstacles whose depths oscillate over a common period, sampled at ``num_keyframes`` keyframes.

    Obstacle k sits at ``center_xy_m[k]`` (X right, Y down, metres, left camera frame), is ``size_m[k]`` wide
    and high (metres), and its depth follows ``mid + amp · sin(2π (cycles_k · t / period_s) + phase_k)`` with
    ``mid ± amp = depth_range_m``, so every track is periodic in ``period_s``. ``floor_height_m``: the cameras
    that high over a floor, pitched down ``camera_pitch_deg`` (a walker's view: the floor is not an obstacle, and
    ``guide`` must not warn of it); None: no floor. ``heap_ahead_m``: a heap of rocks on that floor, this far ahead
    in the middle of the view, of ``svs_torch.data.heap_rendering.WALKER_HEAP_RADIUS_M`` and ``_HEIGHT_M`` (an
    obstacle ``guide`` must warn of); None: none. Only the svs_torch renderer draws the floor and the heap.
    """

    def __init__(self, depth_range_m: tuple[float, float] = (0.8, 3.0), period_s: float = 12.0,
                 num_keyframes: int = 24, floor_height_m: float | None = None, camera_pitch_deg: float = 0.0,
                 heap_ahead_m: float | None = None) -> None:
        if heap_ahead_m is not None and (floor_height_m is None or not heap_ahead_m > 0):
            raise ValueError(f"heap_ahead_m: expected a distance > 0 metres on a floor (give floor_height_m), got "
                             f"{heap_ahead_m!r} with floor_height_m={floor_height_m!r}")
        self.center_xy_m = np.array([[-0.25, 0.0], [0.3, 0.05]])
        self.size_m = np.array([[0.30, 0.50], [0.25, 0.35]])
        self.cycles = np.array([1.0, 2.0])  # oscillations per period, one per obstacle
        self.phase = np.array([0.0, 2.0])  # radians
        self.depth_range_m = depth_range_m
        self.period_s = period_s
        self.num_keyframes = num_keyframes
        self.floor_height_m = floor_height_m
        self.camera_pitch_deg = camera_pitch_deg
        self.heap_ahead_m = heap_ahead_m

    def keyframe(self, time_s: float) -> int:
        """Index of the keyframe shown at ``time_s`` (keyframes are ``period_s / num_keyframes`` apart)."""
        return int(math.floor(time_s / self.period_s * self.num_keyframes)) % self.num_keyframes

    def depths_m(self, keyframe: int) -> np.ndarray:
        """Depth of each obstacle at a keyframe, metres, shape (K,)."""
        lo, hi = self.depth_range_m
        angle = 2 * math.pi * self.cycles * keyframe / self.num_keyframes + self.phase
        return (lo + hi) / 2 + (hi - lo) / 2 * np.sin(angle)


def render_simple_pair(depths_m: np.ndarray, center_xy_m: np.ndarray, size_m: np.ndarray, size_wh: tuple[int, int],
                       camera: SVSCamera = SVS_CAMERA, background_depth_m: float = WALL_DEPTH_M,
                       seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A fast stand-in renderer: bright textured rectangles over a dark textured wall, each shifted by its disparity.

    Textures are fixed per image (not per surface), so ``L(x) ≈ R(x − d)`` holds inside each rectangle and on the
    wall away from the rectangles. Returns left and right ``(H, W)`` uint8.
    """
    width, height = size_wh
    focal = camera.focal_px(width)
    rng = np.random.default_rng(seed)
    wall_shift = int(round(focal * camera.baseline_m / background_depth_m))
    wall = cv2.resize(rng.uniform(25, 100, (height // 4 + 1, (width + wall_shift) // 4 + 1)),
                      (width + wall_shift, height), interpolation=cv2.INTER_NEAREST)
    # L(x) = R(x − d): the right view sees the wall shifted by its disparity (the two slices the other way round
    # gave the wall a disparity of −d, which the pipeline ranged as obstacles 0.3-0.6 m ahead: "Stop").
    left = wall[:, :width].copy()
    right = wall[:, wall_shift:].copy()
    cx, cy = camera.principal_point_px(width, height)
    for k in np.argsort(-depths_m):  # far to near: nearer rectangles paint over farther ones
        z = float(depths_m[k])
        w_px, h_px = (max(2, int(round(focal * s / z))) for s in size_m[k])
        x0 = int(round(cx + focal * center_xy_m[k, 0] / z - w_px / 2))
        y0 = int(round(cy + focal * center_xy_m[k, 1] / z - h_px / 2))
        texture = cv2.resize(rng.uniform(135, 235, (max(1, h_px // 6), max(1, w_px // 6))), (w_px, h_px),
                             interpolation=cv2.INTER_NEAREST)
        disparity = int(round(focal * camera.baseline_m / z))
        for image, x_start in ((left, x0), (right, x0 - disparity)):
            _paste(image, texture, x_start, y0)
    return left.astype(np.uint8), right.astype(np.uint8)


def _paste(image: np.ndarray, patch: np.ndarray, x0: int, y0: int) -> None:
    height, width = image.shape
    xa, ya = max(0, x0), max(0, y0)
    xb, yb = min(width, x0 + patch.shape[1]), min(height, y0 + patch.shape[0])
    if xa < xb and ya < yb:
        image[ya:yb, xa:xb] = patch[ya - y0:yb - y0, xa - x0:xb - x0]


def _render_torch_pair(track: ObstacleTrack, keyframe: int, size_wh: tuple[int, int], camera: SVSCamera,
                       seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One keyframe through ``svs_torch.data.synthetic.render_obstacle_scenes``; left, right (H, W) uint8."""
    import torch
    from svs_torch.data.heap_rendering import WALKER_HEAP_HEIGHT_M, WALKER_HEAP_RADIUS_M
    from svs_torch.data.synthetic import render_obstacle_scenes

    depths = torch.tensor(track.depths_m(keyframe), dtype=torch.float32).unsqueeze(0)  # (1, K)
    heaps = None if track.heap_ahead_m is None else torch.tensor([[0.0, track.heap_ahead_m, WALKER_HEAP_RADIUS_M,
                                                                    WALKER_HEAP_HEIGHT_M]])
    scenes = render_obstacle_scenes(depths, torch.tensor(track.center_xy_m, dtype=torch.float32).unsqueeze(0),
                                    torch.tensor(track.size_m, dtype=torch.float32).unsqueeze(0),
                                    size_wh=size_wh, camera=camera, generator=torch.Generator().manual_seed(seed),
                                    floor_height_m=track.floor_height_m, camera_pitch_deg=track.camera_pitch_deg,
                                    heaps=heaps)

    def to_u8(image: torch.Tensor) -> np.ndarray:
        return (image[0, 0] * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()

    return to_u8(scenes.batch.left), to_u8(scenes.batch.right)


class SyntheticSource:
    """Moving obstacles at known depths (:class:`ObstacleTrack`), as a thread-safe frame source.

    With ``renderer="torch"`` (default) keyframes come from ``render_obstacle_scenes``, rendered once per size in
    a background thread (a few tenths of a second each on a CPU); until a size's keyframe is ready the source
    serves the nearest ready keyframe, else :func:`render_simple_pair`. ``renderer="simple"`` uses only the
    fast renderer. If ``svs_torch.data.synthetic`` cannot be imported the source falls back to ``"simple"``.
    """

    def __init__(self, track: ObstacleTrack | None = None, renderer: str = "torch", camera: SVSCamera = SVS_CAMERA,
                 seed: int = 0) -> None:
        if renderer not in ("torch", "simple"):
            raise ValueError(f"renderer: expected 'torch' or 'simple', got {renderer!r}")
        if renderer == "torch":
            try:
                import svs_torch.data.synthetic  # noqa: F401  (checked here so a missing module falls back)
            except ImportError:
                renderer = "simple"
        self.track = track or ObstacleTrack()
        self.renderer = renderer
        self.camera = camera
        self.seed = seed
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._torch: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._simple: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._wanted: list[tuple[int, int]] = []
        self._recent: dict[tuple[int, int], int] = {}  # last keyframe asked for, per size
        self._closed = False
        self._thread: threading.Thread | None = None

    def depths_m(self, time_s: float) -> np.ndarray:
        """Obstacle depths (K,) in metres of the frame served at ``time_s``."""
        return self.track.depths_m(self.track.keyframe(time_s))

    def __call__(self, camera: str, width: int, height: int, time_s: float) -> np.ndarray:
        keyframe = self.track.keyframe(time_s)
        pair = self._torch_pair((width, height), keyframe) if self.renderer == "torch" else None
        if pair is None:
            pair = self._simple_pair((width, height), keyframe)
        return pair[0] if camera == "left" else pair[1]

    def prepare(self, size_wh: tuple[int, int], timeout_s: float = 60.0, *, complete: bool = True) -> bool:
        """Block until every keyframe (``complete``) or one keyframe at ``size_wh`` is rendered; False on timeout.

        Until every keyframe is rendered, a frame may show the nearest rendered keyframe instead of the current
        one, so :meth:`depths_m` is exact only after ``prepare(size_wh)``.
        """
        if self.renderer != "torch":
            return True
        size_wh = tuple(size_wh)

        def done() -> bool:
            if complete:
                return self._complete(size_wh)
            return any(key[:2] == size_wh for key in self._torch)

        # Polled under the plain lock, not waited on the Condition: a Ctrl-C that landed as the Condition's
        # __enter__ (Python) took the lock left it held, and close() then waited on it for good (guide --emulator,
        # an audit that interrupted each place in turn: tests/cli/test_interrupts).
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                self._want(size_wh)
                if done():
                    return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(PREPARE_POLL_S)

    def close(self) -> None:
        """Stop the background renderer: it finishes the keyframe in hand, which is waited for (up to
        :data:`RENDER_STOP_TIMEOUT_S`). Why: a 640x480 or 1280x1024 keyframe takes seconds on a loaded machine, and
        a render thread still inside torch when the process exits aborted it after its work was done ("terminate
        called without an active exception", exit 134: ``guide --emulator --size 640x480``, an audit)."""
        with self._lock:  # (not the Condition: see prepare)
            self._closed = True
            self._wake.notify_all()
        if self._thread is not None:
            with contextlib.suppress(RuntimeError):  # a start() that a Ctrl-C cut short: the thread never began
                self._thread.join(timeout=RENDER_STOP_TIMEOUT_S)

    def _complete(self, size_wh: tuple[int, int]) -> bool:
        return all((*size_wh, i) in self._torch for i in range(self.track.num_keyframes))

    def _want(self, size_wh: tuple[int, int]) -> None:
        """Queue a size for background rendering (lock held)."""
        if size_wh not in self._wanted and not self._complete(size_wh):
            self._wanted.append(size_wh)
            self._wake.notify_all()
        if self._thread is None and not self._closed:
            self._thread = threading.Thread(target=self._render_loop, name="svs-emulator-render", daemon=True)
            self._thread.start()

    def _torch_pair(self, size_wh: tuple[int, int], keyframe: int) -> tuple[np.ndarray, np.ndarray] | None:
        with self._lock:
            self._want(size_wh)
            self._recent[size_wh] = keyframe
            num = self.track.num_keyframes
            for offset in range(num):  # nearest ready keyframe, looking back in time first
                for index in ((keyframe - offset) % num, (keyframe + offset) % num):
                    pair = self._torch.get((*size_wh, index))
                    if pair is not None:
                        return pair
        return None

    def _simple_pair(self, size_wh: tuple[int, int], keyframe: int) -> tuple[np.ndarray, np.ndarray]:
        key = (*size_wh, keyframe)
        with self._lock:
            pair = self._simple.get(key)
        if pair is None:
            track = self.track
            pair = render_simple_pair(track.depths_m(keyframe), track.center_xy_m, track.size_m, size_wh,
                                      self.camera, seed=self.seed)
            with self._lock:
                self._simple[key] = pair
        return pair

    def _render_loop(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._closed or bool(self._wanted))
                if self._closed:
                    return
                size_wh = self._wanted[0]
                num = self.track.num_keyframes
                missing = [i for i in range(num) if (*size_wh, i) not in self._torch]
                if not missing:
                    self._wanted.pop(0)
                    self._wake.notify_all()
                    continue
                # The keyframe shown now first, then the ones coming next: the source catches up with the clock.
                now = self._recent.get(size_wh, 0)
                keyframe = min(missing, key=lambda i: (i - now) % num)
            pair = _render_torch_pair(self.track, keyframe, size_wh, self.camera, self.seed)
            with self._wake:
                self._torch[(*size_wh, keyframe)] = pair
                self._wake.notify_all()


class ImageFolderSource:
    """Stereo pairs from a folder, resized to the requested size, advancing one pair every ``step_s`` seconds.

    Layouts: ``DIR/left/*`` with ``DIR/right/*`` (paired in sorted order), or files in ``DIR`` whose names contain
    ``left`` with a partner where ``left`` is replaced by ``right`` (``left01.jpg`` / ``right01.jpg``).
    """

    def __init__(self, folder: str | Path, step_s: float = 1.0) -> None:
        folder = Path(folder)
        self.pairs = _find_pairs(folder)
        if not self.pairs:
            raise ValueError(f"images: no left/right image pairs found in {folder} (expected left/ and right/ "
                             "subfolders, or files named like left01.png / right01.png)")
        # Every file checked at start (its header, not decoded): an empty or foreign file killed a board's thread
        # at its first grab of that pair.
        unreadable = next((path for pair in self.pairs for path in pair if not cv2.haveImageReader(str(path))), None)
        if unreadable is not None:
            raise ValueError(f"images: {unreadable} is not an image OpenCV can read")
        if not (step_s >= MIN_IMAGE_STEP_S and math.isfinite(step_s)):
            raise ValueError(f"step_s: expected a finite number of seconds >= {MIN_IMAGE_STEP_S:g}, got {step_s!r}")
        self.step_s = step_s
        self._lock = threading.Lock()
        self._cache: dict[tuple[int, int, int, str], np.ndarray] = {}

    def __call__(self, camera: str, width: int, height: int, time_s: float) -> np.ndarray:
        index = int(math.floor(time_s / self.step_s)) % len(self.pairs)
        key = (index, width, height, camera)
        with self._lock:
            image = self._cache.get(key)
        if image is None:
            path = self.pairs[index][0 if camera == "left" else 1]
            raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if raw is None:
                raise ValueError(f"images: cannot read {path}")
            image = cv2.resize(raw, (width, height), interpolation=cv2.INTER_AREA)
            with self._lock:
                self._cache[key] = image
        return image


def _find_pairs(folder: Path) -> list[tuple[Path, Path]]:
    def images(directory: Path) -> list[Path]:
        return sorted(p for p in directory.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)

    if (folder / "left").is_dir() and (folder / "right").is_dir():
        lefts, rights = images(folder / "left"), images(folder / "right")
        if len(lefts) != len(rights):
            raise ValueError(f"images: {folder}/left has {len(lefts)} images but {folder}/right has {len(rights)}")
        return list(zip(lefts, rights))
    pairs = []
    for path in images(folder) if folder.is_dir() else []:
        if "left" in path.name.lower():
            at = path.name.lower().index("left")
            word = path.name[at:at + 4]
            swapped = "RIGHT" if word == "LEFT" else "Right" if word == "Left" else "right"
            partner = path.with_name(path.name[:at] + swapped + path.name[at + 4:])
            if partner.exists():
                pairs.append((path, partner))
    return pairs
