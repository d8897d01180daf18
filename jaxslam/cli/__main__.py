"""``python -m jaxslam.cli``: the ``jaxslam`` command."""

import sys

from jaxslam.cli import main

sys.exit(main())
