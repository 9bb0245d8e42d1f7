"""``python -m slamreplay.api.cli``: the ``slamreplay`` command."""

import sys

from slamreplay.api.cli.command import main

sys.exit(main())
