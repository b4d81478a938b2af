"""The one base class of every error a user's input can cause.

A bad configuration, an unusable scene file, a missing or corrupt checkpoint, a
pre-trained directory that cannot be read, a run that cannot go on: each raises a
subclass of `UserError` whose message names the problem in one line. The command
lines (`a2catvn_jax.cli`) print that line and exit non-zero instead of a traceback.
"""

from __future__ import annotations


class UserError(Exception):
    """Input the package cannot use; the message says which and why."""


class Interrupted(UserError, RuntimeError):
    """Stopped by Ctrl-C or SIGTERM, after saving what resumes the work (the command
    lines exit with status 130)."""
