"""``python -m sogm_service`` is the ``sogm-service`` command."""

import sys

from sogm_service.apps.cli import main

sys.exit(main())
