"""``python -m eyetohand.cli``: the same as the ``eyetohand`` command."""

import sys

from eyetohand.cli import main

sys.exit(main())
