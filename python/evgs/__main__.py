"""``python -m evgs``: the same as the ``evgs`` command."""

import sys

from evgs.cli import main

sys.exit(main())
