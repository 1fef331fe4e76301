"""Stage 2, features: SURF keypoints and descriptors.

``integral`` (integral images), ``hessian`` (the box-filter Hessian's scale space), ``detector`` (its maxima, refined
into keypoints; :class:`SurfConfig`), ``descriptor`` (SURF descriptors, upright or oriented), ``surf`` (both together:
:func:`extract_surf_features`); ``kernels/`` holds the C kernels of the Hessian, its maxima, their refinement and
the descriptor, beside the torch code that stays their reference.

May import: ``svs_torch.core`` only. Never another stage, the pipeline, ``evaluation``, ``data`` or the CLI.

The names below were the old ``svs_torch.features`` module's, and stay importable from here.
"""

from .detector import SurfConfig
from .surf import SurfFeatures, extract_surf_features

__all__ = ["SurfConfig", "SurfFeatures", "extract_surf_features"]
