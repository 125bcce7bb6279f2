"""``python -m server.cli``: the same as ``motiond``."""

import sys

from server.cli.main import main

sys.exit(main())
