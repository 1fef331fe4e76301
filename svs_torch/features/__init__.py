"""Stage 2, features: SURF keypoints and descriptors.

``integral`` (integral images), ``hessian`` (the box-filter Hessian's scale space), ``detector`` (its maxima, refined
into keypoints; :class:`SurfConfig`), ``limits`` (the detector's limits and keypoint cap, without torch),
``descriptor`` (SURF descriptors, upright or oriented), ``surf`` (both together: :func:`extract_surf_features`);
``kernels/`` holds the C kernels of the Hessian, its maxima, their refinement and the descriptor, beside the torch
code that stays their reference.

May import: ``svs_torch.core`` only. Never another stage, the pipeline, ``evaluation``, ``data`` or the CLI.

The names below were the old ``svs_torch.features`` module's, and stay importable from here.
"""

from ..core.lazy_names import lazy_names

#: Each name's submodule, imported on first use (PEP 562), so that ``limits`` loads without torch: the command
#: line's ``--help`` quotes it.
_SUBMODULE = {"SurfConfig": "detector", "SurfFeatures": "surf", "extract_surf_features": "surf"}
__getattr__, __dir__ = lazy_names(__name__, _SUBMODULE)
__all__ = sorted(_SUBMODULE)
