"""What ``svs-depth estimate`` says of a loosely mounted right camera whose rows the pipeline aligned to the left
camera's (``PipelineConfig.row_alignment``): how far the alignment rolled, shifted and scaled its view, and turned
it about its y and x axes (a keystone), so that a developer sees how far the board is off and which way. Read from
the pair's rows: exact for a rig's roll, height and zoom difference (experiments/real_rig.py's misalignments read
back within 0.1°, 0.5 px, 0.3 %), while a wide lens's distortion and a near scene's vertical disparities add
their own (OpenCV's chessboard pairs: rolls of −0.3 to −1.5° where ``calibrate`` measures the pose at −0.2°); the
pose itself is ``svs-depth calibrate``'s. The alignment undoes all of it before depth is measured."""

from __future__ import annotations

__all__ = ["RIGHT_CAMERA_KEYS", "right_camera_line", "right_camera_report"]

#: The report's keys, null where the rows were not aligned.
RIGHT_CAMERA_KEYS = ("right_camera_turn_deg", "right_camera_roll_deg", "right_camera_shift_y_px",
                     "right_camera_scale_pct")


def right_camera_report(result, index: int, factors: tuple[float, float], image_hw: tuple[int, int]) -> dict:
    """The :data:`RIGHT_CAMERA_KEYS` of pair ``index`` of a :class:`~svs_torch.pipeline.PipelineResult` run at
    ``image_hw`` (its own size, pipeline pixels; ``factors``: input pixels per pipeline pixel, x and y):
    ``right_camera_turn_deg`` [about y, about x], the keystone the alignment undid (null where none), and the roll
    (degrees, positive clockwise on the screen), the vertical shift of the view's centre (input pixels, positive:
    lower) and the scale (percent, positive: larger) of
    :func:`~svs_torch.geometry.row_alignment_keystone.right_camera_deviation`."""
    import torch

    from ..geometry.row_alignment_keystone import right_camera_deviation

    report = dict.fromkeys(RIGHT_CAMERA_KEYS)
    if result.row_aligned is None or not bool(result.row_aligned[index]):
        return report
    turn = result.row_alignment_turn_deg
    if turn is not None and bool((turn[index] != 0).any()):
        report["right_camera_turn_deg"] = [round(float(v), 3) for v in turn[index].tolist()]
    roll, shift, scale = right_camera_deviation(result.H_right[index:index + 1],
                                                torch.tensor([image_hw], dtype=torch.int64))
    report.update(right_camera_roll_deg=round(float(roll), 3),
                  right_camera_shift_y_px=round(float(shift) * factors[1], 2),
                  right_camera_scale_pct=round((float(scale) - 1) * 100, 2))
    return report


def right_camera_line(report: dict) -> str:
    """What the text says of the aligned rows: "its rows aligned to the left camera's (its view rolled 2.0°
    clockwise, 6.0 px lower, 1.0 % larger; turned +1.0° about y, +0.0° about x: undone)"."""
    said = []
    roll, shift, scale = (report.get(key) for key in RIGHT_CAMERA_KEYS[1:])
    if roll is not None:
        said.append(f"its view rolled {abs(roll):.1f}° {'clockwise' if roll >= 0 else 'anticlockwise'}, "
                    f"{abs(shift):.1f} px {'lower' if shift >= 0 else 'higher'}, "
                    f"{abs(scale):.1f} % {'larger' if scale >= 0 else 'smaller'}")
    turn = report.get("right_camera_turn_deg")
    if turn:
        said.append(f"turned {turn[0]:+.1f}° about y, {turn[1]:+.1f}° about x")
    return "its rows aligned to the left camera's" + (f" ({'; '.join(said)}: undone)" if said else "")
