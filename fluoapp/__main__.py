"""``python -m fluoapp``: the ``fluo`` command line (``fluoapp/cli.py``)."""

import sys

from fluoapp.cli import main

sys.exit(main())
