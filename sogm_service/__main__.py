"""``python -m sogm_service`` is the ``sogm-service`` command."""

import sys

from sogm_service.cli import main

sys.exit(main())
