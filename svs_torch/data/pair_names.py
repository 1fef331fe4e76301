"""The names pairs are reported, stored and exported by: a pair that would share its name with another listed pair
(two folders both called ``Teddy``) is labelled with the folders that tell them apart
(:func:`with_distinct_names`); the same files reached through a link are one pair (:func:`pair_identity`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .pair_list import PairSource

__all__ = ["pair_identity", "unusable_name", "with_distinct_names"]


def _loaded_name(source: PairSource) -> str:
    """The name :func:`~svs_torch.data.pair_list.load_pair_source` gives ``source`` without a label."""
    return replace(source, label=None).loaded_name


def with_distinct_names(sources: Sequence[PairSource]) -> list[PairSource]:
    """``sources``, each pair that would share its name with another pair (not the same pair listed again) labelled
    with the folders that tell them apart: ``eval3/Teddy (a)`` and ``eval3/Teddy (b)`` for ``a/Teddy`` and
    ``b/Teddy``. Reports, stores and exported maps then keep them apart (an export is named after the pair)."""
    identities = [None if source.problem is not None else pair_identity(source) for source in sources]
    groups: dict[str, dict[tuple, Path]] = {}
    for source, identity in zip(sources, identities):
        if identity is not None:
            # The first spelling tells a pair apart: it is the one run (unique_sources keeps it), and a repeat
            # through a link, listed later, renamed it (and its exported map) after the link's folder (an audit).
            groups.setdefault(_loaded_name(source), {}).setdefault(identity, Path(os.path.abspath(source.left)))
    labels = {}
    for name, paths in groups.items():
        if len(paths) > 1:
            labels.update(zip(paths, (f"{name} ({tail})" for tail in _telling_folders(list(paths.values())))))
    return [source if identity is None else replace(source, label=labels.get(identity))
            for source, identity in zip(sources, identities)]


def unusable_name(text: str) -> bool:
    """Whether ``text`` holds a character no file's name can: a NUL, or a lone surrogate other than the escapes of
    undecodable bytes (U+DC80-U+DCFF, :func:`os.fsencode`'s ``surrogateescape``). An index.jsonl line (valid JSON,
    ``"L.png\\u0000"`` or ``"\\ud800"``) naming one ended eval in an internal ValueError or UnicodeEncodeError
    from :func:`pair_identity`'s ``realpath`` (an audit)."""
    return any(char == "\0" or "\ud800" <= char <= "\udfff" and not "\udc80" <= char <= "\udcff" for char in text)


def pair_identity(source: PairSource) -> tuple:
    """The files a pair reads, links resolved, and its listed calibration: one scene reached through a symbolic
    link is the same pair, not one to tell apart."""
    return (os.path.realpath(source.left), source.right and os.path.realpath(source.right), source.focal_px,
            source.baseline_m, source.doffs_px)


def _telling_folders(paths: list[Path]) -> list[str]:
    """For each path, the fewest of its parent folders, nearest first, that no other path shares once the parent
    folders all of them end with are left out; numbers where the folders are the same (the same files listed with
    two calibrations)."""
    parents = [path.parent.parts[1 if path.anchor else 0:] for path in paths]  # no root or drive: not a name
    common = 0
    while all(len(parts) > common for parts in parents) and len({parts[-1 - common] for parts in parents}) == 1:
        common += 1
    trimmed = [parts[:len(parts) - common] for parts in parents]
    for count in range(1, max(map(len, trimmed), default=0) + 1):
        tails = ["/".join(parts[-count:]) for parts in trimmed]
        if len(set(tails)) == len(tails) and all(tails):
            return tails
    return [str(number) for number in range(1, len(paths) + 1)]
