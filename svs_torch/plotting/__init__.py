"""Figures: ``figures`` (image panels, label images, writing a figure file), ``plots`` (the pipeline's and the
segmentation's figures) and ``rectified`` (a rectified pair with its epipolar lines).

May import: ``svs_torch.core``, the stages' and the pipeline's public names. Only the CLI and experiments import
it.
"""
