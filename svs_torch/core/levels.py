"""Intensity levels every stage reads alike."""

from __future__ import annotations

__all__ = ["CLIPPED_LEVEL"]

#: A pixel at or above this level is clipped at white (the 8-bit top level, 255 / 255, with room for round-off): a
#: saturated pixel holds no texture, so no matcher measures it (the exposure match and the nearness segmenter's
#: candidate regions read it).
CLIPPED_LEVEL = 254.5 / 255
