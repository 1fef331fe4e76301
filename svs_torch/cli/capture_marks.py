"""What capture's ``index.jsonl`` marks of a listed pair, told by ``estimate --pairs`` and ``eval``.

capture keeps every pair the boards sent and marks the ones guide refuses: ``frozen_camera`` (one board sent its
last frame again while the other's changed; ``"both"``: both boards theirs, for 3 s) and ``time_between_frames_s``
over the camera's :data:`~svs_torch.capture.stereo.MAX_FRAME_GAP_S`; it warns of them at its end. ``estimate --pairs
DIR/index.jsonl`` and ``eval`` then ranged them without a word, as if each were one stereo moment (an audit). They
are still ranged, their numbers unchanged (the index is what the boards sent); each such pair's line says so
(estimate's text, and ``--json`` lines), and the run's end counts them. So are pairs capture grabbed from boards
that answered in each other's roles (``cameras_swapped``: the URLs given the other way round), which ``estimate``
could only ask of ("are LEFT and RIGHT swapped?").

Only the standard library at import: the parent of ``estimate``'s workers never imports torch.
"""

from __future__ import annotations

import warnings

__all__ = ["capture_fields", "capture_warning", "warn_capture_marks"]


def capture_fields(source) -> dict:
    """The JSON fields of a pair whose ``index.jsonl`` line marks it (``source``: a
    :class:`~svs_torch.data.pair_list.PairSource`): ``frozen_camera`` as the index says it (null, ``"left"``,
    ``"right"``) and ``frames_apart_s``, how far apart its two frames came where that is over
    :data:`~svs_torch.capture.stereo.MAX_FRAME_GAP_S` (null: within it), and ``cameras_swapped`` (true) where the
    index says so; {} for a pair the index does not mark, and for any other entry (a sound pair's line is as it
    was: guide's record lines are all sound pairs)."""
    if source.problem is not None:  # (only an index line carries the marks: a plain list's pair has neither)
        return {}
    from ..capture.stereo import MAX_FRAME_GAP_S

    gap_s = source.time_between_frames_s
    apart = gap_s is not None and abs(gap_s) > MAX_FRAME_GAP_S
    swapped = {"cameras_swapped": True} if source.cameras_swapped else {}
    if not (apart or source.frozen_camera):
        return swapped
    return {"frozen_camera": source.frozen_camera, "frames_apart_s": round(abs(gap_s), 3) if apart else None,
            **swapped}


def capture_warning(fields: dict) -> str | None:
    """The one line a pair's :func:`capture_fields` (or a report holding them) warrants, None for a sound pair."""
    said = []
    if fields.get("frozen_camera"):
        camera = fields["frozen_camera"]
        said.append("both cameras' frames were sent again, an old pair (frozen_camera in the index)"
                    if camera == "both" else f"the {camera} camera's frame was sent again while the {_other(camera)} "
                    "one's changed (frozen_camera in the index)")
    if fields.get("frames_apart_s") is not None:
        said.append(f"its frames came {fields['frames_apart_s']:.2f} s apart (time_between_frames_s in the index)")
    # (both boards stalled send one stereo moment, but an old one)
    moment = "not the moment grabbed" if len(said) == 1 and fields.get("frozen_camera") == "both" else \
        "not one stereo moment"
    said = [f"{'; '.join(said)}: {moment}"] if said else []
    if fields.get("cameras_swapped"):
        said.append("captured from boards answering in each other's roles (cameras_swapped in the index): its left "
                    f"image is {_SWAPPED}")
    return f"warning: {'; '.join(said)}" if said else None


def warn_capture_marks(lines: list[dict], total: int) -> None:
    """Warn, one line a kind, of the pairs among ``lines`` (each with its :func:`capture_fields`) that capture's
    index marks, of the ``total`` listed."""
    frozen = {camera: sum(line.get("frozen_camera") == camera for line in lines) for camera in ("left", "right")}
    apart = [line["frames_apart_s"] for line in lines if line.get("frames_apart_s") is not None]
    if both := sum(line.get("frozen_camera") == "both" for line in lines):
        warnings.warn(f"{both} of {total} listed pairs have both cameras' frames sent again for 3 s or more "
                      "(frozen_camera \"both\" in the index and in each --json line): ranged, but an old pair again "
                      "and again, both boards stalled; guide does not range such pairs", RuntimeWarning, stacklevel=2)
    for camera, count in frozen.items():
        if count:
            warnings.warn(f"{count} of {total} listed pairs have the {camera} camera's frame sent again while the "
                          f"{_other(camera)} one's changed (frozen_camera in the index and in each --json line): "
                          "ranged, but not one stereo moment (an old view beside a new one); guide does not range "
                          "such pairs", RuntimeWarning, stacklevel=2)
    if swapped := sum(bool(line.get("cameras_swapped")) for line in lines):
        warnings.warn(f"{swapped} of {total} listed pairs were captured from boards answering in each other's roles "
                      f"(cameras_swapped in the index and in each --json line): ranged, but each left image is "
                      f"{_SWAPPED}",
                      RuntimeWarning, stacklevel=2)
    if apart:
        warnings.warn(f"{len(apart)} of {total} listed pairs' frames came too far apart to be one stereo moment (up "
                      f"to {max(apart):.2f} s; time_between_frames_s in the index, frames_apart_s in each --json "
                      "line): ranged, but the scene and the cameras moved between them; guide does not range such "
                      "pairs", RuntimeWarning, stacklevel=2)


#: What a pair captured from boards in each other's roles is (capture's warning says the same).
_SWAPPED = "likely the right camera's view; capture again with --left and --right the other way round"


def _other(camera: str) -> str:
    return "right" if camera == "left" else "left"
