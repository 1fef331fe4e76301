"""``python -m svs_torch.cli``: the same as the ``svs-depth`` console script."""

import sys

from . import main

sys.exit(main())
