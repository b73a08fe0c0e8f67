"""``python -m bridge.cli``: the same as the ``koala-bridge`` console script."""

import sys

from bridge.cli.main import main

sys.exit(main())
