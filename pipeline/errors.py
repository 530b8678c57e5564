"""User errors: problems the person running the pipeline can fix (bad params, missing files, bad TOML).

The rule, used by the CLI and the run records: an exception is a *user error* when its class is a
subclass of `UserError` or carries the class attribute `user_error = True`. The attribute form exists
for code that must not import the engine (the `dualnerf/` library), e.g.

    class DatasetError(ValueError):
        user_error = True

User errors print their message and exit with status 2, without a traceback; anything else is an
internal error: traceback, exit status 1.
"""
from __future__ import annotations


class UserError(ValueError):
    """Base class for problems in what the user supplied; the message says what and where."""

    user_error = True


def is_user_error(exc: BaseException) -> bool:
    return isinstance(exc, UserError) or getattr(type(exc), "user_error", False) is True


def describe(exc: BaseException) -> str:
    """One line naming the exception class and its message (used in run records and status)."""
    message = str(exc).strip()
    return f"{type(exc).__name__}: {message}" if message else type(exc).__name__
