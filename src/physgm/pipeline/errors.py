"""The one error type the pipeline shows to users as ``error: ...`` (exit code 2, no traceback)."""

from __future__ import annotations


class UserError(Exception):
    """Bad input or settings: the message says what was wrong and what to do.

    Anything else that escapes the pipeline is a bug and keeps its traceback.
    """
