"""``python -m agentsdk.cli``: the ``agentsdk`` command line."""

import sys

from ._main import main

sys.exit(main())
