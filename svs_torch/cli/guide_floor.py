"""Which distances ``guide`` warns on (:class:`FloorMemory`): along the floor the pair's floor rule found, the one
found last, a level floor under the camera as worn, or the camera's axis (:mod:`svs_torch.depth.floor_distance`)."""

from __future__ import annotations

from ..depth.floor_distance import pitched_camera
from ..pipeline import result_along_floor

__all__ = ["DISTANCE_ALONG", "FLOOR_MEMORY_S", "FloorMemory"]

#: Seconds ``guide`` reads its distances along the floor it last found, on pairs where its floor rule finds none:
#: a camera frame's noise hides the floor from the rule on some pairs (rendered walker scenes as the board's digit
#: 4 frames: found on 49 of 70, experiments/floor_distance.md), while the camera, worn on the walker's body, keeps
#: its pose over the floor; a pair ranged along the camera's axis among pairs ranged along the floor moved the
#: warned distance by 0.2-0.4 m from one pair to the next. Longer, a walker who bent or turned would be ranged
#: along a floor no longer under the camera.
FLOOR_MEMORY_S = 2.0
#: What a warning's distance runs along (``guide --json``'s ``warning.distance_along``): the floor found in the pair,
#: the one found last (:data:`FLOOR_MEMORY_S`), a level floor under the camera as worn (``--camera-pitch-deg``), or
#: the camera's axis.
DISTANCE_ALONG = ("floor", "remembered_floor", "camera_pitch", "axis")


class FloorMemory:
    """Which distances ``guide`` warns on (:mod:`svs_torch.depth.floor_distance`): where the pair's floor rule found
    the floor, the obstacle nearest ahead along it (a walker's camera is pitched down, and depth along its axis puts
    what lies on the floor 0.2-0.4 m farther than it stands); on a pair where it found none, along the floor found
    last, for ``memory_s`` seconds (:data:`FLOOR_MEMORY_S`); else along a level floor under the camera pitched
    ``worn_pitch_deg`` (``--camera-pitch-deg``, the rig as worn) where given; else along the camera's axis, as
    ``estimate`` ranges. :meth:`nearest` says which (:data:`DISTANCE_ALONG`)."""

    def __init__(self, memory_s: float = FLOOR_MEMORY_S, worn_pitch_deg: float | None = None) -> None:
        self.memory_s, self.worn_pitch_deg = memory_s, worn_pitch_deg
        self.floor = None  # the FloorGeometry found last
        self.found_s: float | None = None

    def nearest(self, result, now_s: float) -> tuple:
        """The nearest obstacle of a one-pair ``result`` to warn of, what its distances run along (one of
        :data:`DISTANCE_ALONG`) and the age in seconds of the floor found that they run along (0: the pair's own;
        None: not a floor found)."""
        distances = getattr(result, "floor", None)  # (a result of the paper's rule has no dense map, nor this)
        if distances is not None and bool(distances.floor.found[0]):
            self.floor, self.found_s = distances.floor, now_s
            return distances.nearest, "floor", 0.0
        if self.floor is not None and now_s - self.found_s <= self.memory_s:
            remembered = result_along_floor(result, self.floor)  # (None without a dense map)
            if remembered is not None:
                return remembered.nearest, "remembered_floor", now_s - self.found_s
        if self.worn_pitch_deg is not None:
            pitched = result_along_floor(result, pitched_camera(self.worn_pitch_deg, 1, result.status.device))
            if pitched is not None:
                return pitched.nearest, "camera_pitch", None
        return result.depth.nearest, "axis", None
