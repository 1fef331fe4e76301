"""What ``svs-depth capture`` judges of the pairs it keeps, and marks in ``index.jsonl`` and warns of at its end.

capture keeps every pair the boards sent (it records, guide refuses); :class:`PairChecks` counts the ones guide
would not range, and tells which boards answered in each other's roles (``cameras_swapped``).
"""

from __future__ import annotations

from types import SimpleNamespace

__all__ = ["PairChecks"]


class PairChecks:
    """What capture counts of the pairs it keeps, as guide refuses them: pairs whose two frames came more than
    ``camera.max_frame_gap_s`` apart after their regrabs (a right board 0.5 s late on every frame was saved pair
    after pair without a word), and pairs in which one camera sent its last frame again while the other's changed
    (:class:`~svs_torch.capture.frozen.FrozenCameraWatch`: a stalled board's pairs were saved without a word, an old
    view beside a new one in a data set), and pairs whose two frames are one image (guide's identical_views, warned
    of only); and the boards' roles (:attr:`swapped`, the camera's
    :attr:`~svs_torch.capture.stereo.SVSStereoCamera.roles_swapped`). All are kept: capture records what
    the boards sent, and the index says which of the first two they are, and whether the roles were swapped."""

    def __init__(self, camera) -> None:
        from ..capture.frozen import FrozenCameraWatch

        self.max_frame_gap_s, self.watch = camera.max_frame_gap_s, FrozenCameraWatch()
        self.apart, self.frozen, self.one_image = 0, {"left": 0, "right": 0, "both": 0}, 0
        self.swapped = camera.roles_swapped  # the index's cameras_swapped of every pair
        self.roles = {name: version.role for name, version in camera.versions.items()}

    def frozen_camera(self, pair) -> str | None:
        """The camera of ``pair`` (a :class:`~svs_torch.capture.stereo.StereoPair`) judged frozen, or None; each
        pair in the order grabbed (compared with the one before it)."""
        left, right = self._frames(pair)
        # With the time, as guide judges it: both boards stalled (both frames the same again for BOTH_FROZEN_S) were
        # not judged, and their one old pair was saved again and again, neither marked nor warned of (an audit)
        return self.watch.update(SimpleNamespace(left=left, right=right), pair.left.arrival_monotonic_s)

    @staticmethod
    def _frames(pair) -> tuple:
        """The decoded grayscale frames of ``pair`` as tensors, guide's, without a copy."""
        import torch

        return torch.from_numpy(pair.left.image), torch.from_numpy(pair.right.image)

    def count(self, pair, frozen: str | None) -> None:
        """Count a kept ``pair``, ``frozen`` its :meth:`frozen_camera`."""
        from ..capture.frozen import one_image_twice

        gap_s = self.max_frame_gap_s
        self.apart += gap_s is not None and abs(pair.time_between_frames_s) > gap_s
        if frozen is not None:
            self.frozen[frozen] += 1
        # One image for both cameras (guide's identical_views): such pairs were saved without a word, though guide
        # refuses them (an audit).
        self.one_image += one_image_twice(*self._frames(pair))

    def warnings(self, done: int) -> list[str]:
        """The warnings of a capture that kept ``done`` pairs: one line each, none when all pairs were sound."""
        said = []
        if self.swapped and done:
            said.append(f"the left board answered as the stereo {self.roles['left']} and the right as the "
                        f"{self.roles['right']} (cameras_swapped in index.jsonl, on each of the {done} pairs kept): "
                        "each left image is likely the right camera's view (estimate asks of such pairs whether "
                        "LEFT and RIGHT are swapped); cover the left lens to confirm, then capture again with the "
                        "--left and --right URLs the other way round")
        if self.apart:
            said.append(f"{self.apart} of {done} pairs' frames came over {self.max_frame_gap_s:g} s apart after "
                        "their regrabs (time_between_frames_s in index.jsonl): not one stereo moment; guide does not "
                        "range such pairs")
        if self.frozen["both"]:
            said.append(f"{self.frozen['both']} of {done} pairs have both cameras' frames sent again, pixel for pixel, "
                        "for 3 s or more (frozen_camera \"both\" in index.jsonl): both boards stalled, one old pair "
                        "again and again; check the cameras; guide does not range such pairs")
        for camera, count in self.frozen.items():
            if count and camera != "both":
                other = "right" if camera == "left" else "left"
                said.append(f"{count} of {done} pairs have the {camera} camera's frame sent again, pixel for pixel, "
                            f"while the {other} one's changed (frozen_camera in index.jsonl): a stalled board, an old "
                            f"view beside a new one; check the {camera} camera; guide does not range such pairs")
        if self.one_image:
            said.append(f"{self.one_image} of {done} pairs have one image for both cameras, pixel for pixel: one "
                        "board's frame sent for both (check --left and --right reach two boards); guide does not "
                        "range such pairs")
        return said
