"""The types of a settings dataclass's values, checked as it is made.

Settings arrive from the command line through Hydra as whatever the user typed: ``planner.allow_rigid=maybe``
is the string "maybe", which Python takes as true, and ``solver.cfl=fast`` fails later in a comparison
with a message about ``<``. ``check_types`` turns both into a message that names the setting.
"""

from __future__ import annotations

from dataclasses import fields
from numbers import Real


def check_types(settings, label: str) -> None:
    """Raise ValueError naming ``label`` (e.g. "planner setting") and the field whose value is not
    of its declared type: bool fields want True or False, int fields an integer, float fields a
    number (an int is a number; True and False are not). None passes, since several settings take
    null for "the default" without saying so in their type; other fields are not checked."""
    for f in fields(settings):
        value = getattr(settings, f.name)
        if value is None:
            continue
        kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
        if kind == "bool" and not isinstance(value, bool):
            raise ValueError(f"{label} {f.name}={value!r} must be true or false")
        if kind in ("int", "float") and (isinstance(value, bool) or not isinstance(value, Real)):
            raise ValueError(f"{label} {f.name}={value!r} must be a number")
        if kind == "int" and value != int(value):
            raise ValueError(f"{label} {f.name}={value!r} must be an integer")
