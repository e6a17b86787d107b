"""The one error type shown to users as ``error: ...`` (exit code 2, no traceback)."""

from __future__ import annotations


class UserError(Exception):
    """Bad input, settings or files: the message says what was wrong and what to do.

    Anything else that escapes the pipeline is a bug and keeps its traceback.
    """
