"""``python -m eyetohand.cli``: the same as the ``eyetohand`` command."""

import sys

from . import main

sys.exit(main())
