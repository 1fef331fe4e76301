"""The learned segmenters' weights files: where the shipped ones are (``weights/``), reading one into its
network (once per file and version in a process) and writing one atomically with its metadata.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import torch
from torch import nn

from ..core.checks import InputError
from ..core.files import atomic_output
from ..core.inference import outside_inference_mode
from .network import ObstacleNet, ObstacleNetConfig

__all__ = [
    "NEARNESS_WEIGHTS", "SHIPPED_WEIGHTS", "cached_obstacle_net", "check_weights_file", "load_obstacle_net",
    "save_obstacle_net", "weights_path"
]


#: The weights shipped inside the package (``SegmentationConfig(segmenter="learned")``).
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "obstacle_net.pt"
#: The nearness segmenter's shipped correction network (``SegmentationConfig(segmenter="nearness")``, issue 32).
NEARNESS_WEIGHTS = Path(__file__).resolve().parent / "weights" / "nearness_net.pt"
_FORMAT = "svs_torch.obstacle_net/1"
#: Each segmenter kind's weights-file format (the classes: :func:`_network_classes`).
_KINDS = {"learned": _FORMAT, "nearness": "svs_torch.nearness_net/1"}


def weights_path(segmenter: str) -> Path:
    """The weights file of a ``SegmentationConfig.segmenter`` value: ``"learned"`` / ``"nearness"`` the shipped
    one, ``"learned:PATH"`` / ``"nearness:PATH"`` PATH."""
    if not isinstance(segmenter, str):  # a Path of weights gave AttributeError: 'PosixPath' ... 'partition'
        raise InputError(f"segmenter: expected learned, learned:PATH, nearness or nearness:PATH (a str), got "
                         f"{type(segmenter).__name__} {str(segmenter)!r:.80}")
    kind, _, path = segmenter.partition(":")
    if kind in _KINDS and path:
        return Path(path).expanduser()
    if kind in _KINDS and ":" not in segmenter:
        return SHIPPED_WEIGHTS if kind == "learned" else NEARNESS_WEIGHTS
    raise InputError(f"segmenter: expected learned, learned:PATH, nearness or nearness:PATH, got {segmenter!r}")


def _network_classes(kind: str) -> tuple[type[nn.Module], type]:
    from .nearness import NearnessNet, NearnessNetConfig
    return (ObstacleNet, ObstacleNetConfig) if kind == "learned" else (NearnessNet, NearnessNetConfig)


def load_obstacle_net(segmenter: str = "learned") -> nn.Module:
    """The network of ``"learned"`` / ``"nearness"`` (shipped) or ``"learned:PATH"`` / ``"nearness:PATH"``: an
    :class:`ObstacleNet` or a :class:`~svs_torch.segmentation.nearness.NearnessNet`, in float32 and eval mode.

    Raises:
        InputError: one line, naming the file, when it is missing, not a weights file, or does not fit.
    """
    path = weights_path(segmenter)
    if not path.is_file():
        raise InputError(f"segmenter: no weights file at {str(path)!r}")
    try:
        stored = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch.load raises many types (zip, pickle, EOF, OS); all mean "not a weights file"
        # Its own text advises loading with weights_only=False, which would run code from an untrusted file.
        raise InputError(f"segmenter: {str(path)!r} is not a weights file (not tensors saved by torch.save: "
                         f"{type(error).__name__})") from None
    kind = segmenter.partition(":")[0]
    expected = _KINDS[kind]
    if not isinstance(stored, dict) or stored.get("format") != expected:
        found = stored.get("format") if isinstance(stored, dict) else None
        other = next((name for name, tag in _KINDS.items() if tag == found), None)
        if other is not None:  # the kinds' files swapped: the fix is the prefix
            raise InputError(f"segmenter: {str(path)!r} is a {other} network file, not a {kind} one (give it as "
                             f"{other}:PATH)")
        if isinstance(found, str) and found.partition("/")[0] == expected.partition("/")[0]:
            raise InputError(f"segmenter: {str(path)!r} is in format {found}, which this svs_torch does not read (it "
                             f"reads {expected}; written by another version of svs_torch?)")
        found = f", found {found!r}" if isinstance(stored, dict) and "format" in stored else ""
        raise InputError(f"segmenter: {str(path)!r} is not a svs_torch {kind} network file (format {expected}"
                         f"{found})")
    network_class, config_class = _network_classes(kind)
    try:
        settings = dict(stored["config"])
        unknown = sorted(map(str, set(settings) - {field.name for field in dataclasses.fields(config_class)}))
        if unknown:  # a setting added after this version (the format is kept: older files take the defaults)
            raise InputError(f"{', '.join(unknown)}: not a setting of this svs_torch (written by a newer one?)")
        # The layers' random initial weights are overwritten by the file's: drawn from a forked generator, so that
        # loading (the first pipeline run of a process) leaves torch's global random state as the caller set it.
        with torch.random.fork_rng(devices=[]):
            net = network_class(config_class(**{**settings, "channels": tuple(settings["channels"])}))
        net.load_state_dict(stored["state_dict"])
    except InputError as error:  # a setting out of its range (a hand-edited or foreign file): named without the file
        raise InputError(f"segmenter: {str(path)!r}: its stored settings are refused ({error})") from None
    except (KeyError, TypeError, RuntimeError, ValueError, AttributeError) as error:  # the last two: a file's settings
        # as text (dict("...")) and tensors under numbers (torch's load_state_dict), each a traceback once (an audit)
        reason = " ".join(str(error).split())[:200]
        raise InputError(f"segmenter: {str(path)!r}: the weights do not fit the network ({reason})") from None
    # A diverged run's NaN loaded in silence: in a layer under the shipped zero head the pass was skipped and the file
    # passed for the rule; elsewhere every pair of an eval or a sweep became an ERROR row naming no file (an audit).
    bad = _non_finite_weights(net)
    if bad:
        raise InputError(f"segmenter: {str(path)!r}: its weights hold NaN or inf ({bad}: a diverged training run?)")
    return net.float().eval()


def _non_finite_weights(net: nn.Module) -> str:
    """The names of ``net``'s tensors holding a NaN or an infinity (the first three), or ``""``."""
    bad = [name for name, value in net.state_dict().items() if not bool(torch.isfinite(value).all())]
    return ", ".join(bad[:3]) + (", ..." if len(bad) > 3 else "")


_NET_CACHE: dict[tuple[str, str, int, int], nn.Module] = {}


@outside_inference_mode  # the cached network's parameters: never inference tensors (a later call may train through)
def cached_obstacle_net(segmenter: str) -> nn.Module:
    """:func:`load_obstacle_net` once per weights file and version (a batch loop or a sweep does not re-read it
    for every batch; a file rewritten in place, e.g. by a training run, is read again)."""
    path = weights_path(segmenter)
    try:
        stat = path.stat()
    except OSError:
        return load_obstacle_net(segmenter)  # its one-line error
    key = (segmenter.partition(":")[0], str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    if key not in _NET_CACHE:
        _NET_CACHE.clear()  # one network at a time: a sweep over weights files does not pile them up
        _NET_CACHE[key] = load_obstacle_net(segmenter)
    return _NET_CACHE[key]


def check_weights_file(segmenter: str) -> None:
    """Read the weights file a ``"learned:PATH"`` / ``"nearness:PATH"`` names into its network through
    :func:`cached_obstacle_net` (once per file and version; the run that follows takes it from there), so that a
    command refuses a bad file when it checks its arguments, before any work (:func:`load_obstacle_net`'s one-line
    error); the shipped weights and ``"otsu"`` are not read."""
    if isinstance(segmenter, str) and ":" in segmenter:
        cached_obstacle_net(segmenter)


def save_obstacle_net(path: str | Path, net: nn.Module, metadata: dict | None = None) -> None:
    """Write ``net``'s weights, its configuration and ``metadata`` (training settings, split) atomically, in a
    file :func:`load_obstacle_net` reads. ``metadata`` is stored as its JSON form (strings for anything else),
    so the file holds only tensors and plain values and loads with ``weights_only``.

    Raises:
        InputError: ``net``'s weights hold a NaN or an infinity (nothing is written)."""
    path = Path(path)
    # A diverged training run (train_nearness.py --learning-rate 1e30) wrote its NaN weights over the good file at
    # --out, one that load_obstacle_net refuses (an audit): refused here, the file left as it was.
    bad = _non_finite_weights(net)
    if bad:
        raise InputError(f"network: its weights hold NaN or inf ({bad}: a diverged training run?); {str(path)!r} not "
                         "written")
    kind = "learned" if isinstance(net, ObstacleNet) else "nearness"
    stored = {"format": _KINDS[kind], "config": dataclasses.asdict(net.config),
              "state_dict": {k: v.detach().cpu().float() for k, v in net.state_dict().items()},
              "metadata": json.loads(json.dumps(metadata or {}, default=str))}
    path.parent.mkdir(parents=True, exist_ok=True)
    # Through the house's atomic writer: a temporary file of its own (mkstemp) was left beside the weights by a run
    # killed while writing, and torch.save, given its path, named the file's records after it, so the same weights
    # and record made different bytes on every run (an audit). Given a stream, the records are "archive/...".
    with atomic_output(path) as stream:
        torch.save(stored, stream)
