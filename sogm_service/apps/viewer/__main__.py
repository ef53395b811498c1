"""``python -m sogm_service.apps.viewer``: the same as ``sogm-service view``."""

from sogm_service.apps.viewer import main

raise SystemExit(main())
