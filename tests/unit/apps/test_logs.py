"""Logging of the commands (apps/logs): where the lines go."""

from __future__ import annotations

import sys


def test_logging_writes_to_the_stderr_of_the_moment() -> None:
    """A thread that logs after an in-process ``main()`` returned once hit the closed stream
    of pytest's capture ("--- Logging error ---" and a call stack in the next test)."""
    import io
    import logging

    from sogm_service.apps.logs import setup_logging

    root = logging.getLogger()
    saved_handlers, saved_level, saved_stderr = root.handlers[:], root.level, sys.stderr
    first, second = io.StringIO(), io.StringIO()
    try:
        sys.stderr = first
        setup_logging("info")
        logging.getLogger("sogm.test").info("one")
        first.close()
        sys.stderr = second
        logging.getLogger("sogm.test").info("two")
        assert "INFO sogm.test: two" in second.getvalue()
        assert "Logging error" not in second.getvalue()
    finally:
        sys.stderr = saved_stderr
        root.handlers[:] = saved_handlers
        root.setLevel(saved_level)
