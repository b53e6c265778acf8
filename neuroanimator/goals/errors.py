"""Errors of the control-synthesis package (torch-free, so an API process can catch them)."""

from __future__ import annotations


class JobSpecError(ValueError):
    """A job spec that cannot run as given. ``field`` names the offending key (dotted for nested
    ones, e.g. ``optimizer.learning_rate`` or ``terms[1].variable``); the message says what was
    expected and what was got."""

    def __init__(self, field: str, message: str, expected: object = None) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message
        self.expected = expected  # what would have been accepted (the known tasks, ...), when a list says it
