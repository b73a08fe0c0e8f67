"""``python -m koala_bridge``: the same as the ``koala-bridge`` console script."""

import sys

from koala_bridge.cli.main import main

sys.exit(main())
