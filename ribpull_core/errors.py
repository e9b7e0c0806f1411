"""The one error type every RibPull loader and validator raises for bad user input.

A `RibPullInputError` carries a short machine-readable ``code`` (used by the service as the
problem+json ``type`` suffix and ``error.code``) and a message that tells the user what to fix.
Anything else that escapes the core is a bug, not a user error.
"""

from __future__ import annotations


class RibPullInputError(ValueError):
    """Bad input that the user can fix (file content, format, size or parameters).

    Codes in use: ``unknown_format``, ``empty_file``, ``too_few_points``, ``non_finite``,
    ``degenerate``, ``header_mismatch``, ``too_large``, ``parse_error``, ``no_labels``,
    ``bad_parameter``.
    """

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message

    def __str__(self) -> str:  # the message alone reads best on a CLI
        return self.message


class JobCanceled(Exception):
    """Raised inside the pipeline when its cancellation check returns True."""
