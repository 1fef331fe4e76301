"""The small parts every other package shares, and nothing of any stage.

``types`` (the batch and result containers: ``StereoBatch``, ``Keypoints``, ``Matches``, ...), ``errors``
(``InputError``), ``checks`` (argument checks that raise it), ``files`` (paths, atomic writes), ``image_files``
(reading and writing image files), ``camera`` (the SVS camera model), ``ordering`` (stable sort orders),
``mask_reductions`` (fast ``any`` over bool masks), ``numerics`` (a square root with a finite gradient at 0),
``pair_trees`` and ``size_groups`` (taking the pairs of a batch out of a result and putting them back),
``compiling`` (optional ``torch.compile``), ``workers`` (worker processes without torch in the parent),
``lazy_names`` (a package's public names loaded on first use), ``dataset_files`` (the files a dataset's pair is
read from, which no output may overwrite), ``inference`` (the hard pipeline under ``torch.inference_mode``, unseen by
its callers), ``levels`` (the intensity levels every stage reads alike), ``checkout`` (the commit and version that
reports record: ``code_version``), and ``kernels/``, the one loader that builds, caches and opens every stage's C
kernels.

May import: the standard library, torch, numpy, OpenCV, and core itself. Nothing here imports a stage, the
pipeline, ``data``, ``evaluation``, ``plotting``, ``capture`` or the CLI.
"""
