"""What can go wrong in the emulator service, as typed domain errors.

The domain modules (registry, sessions, batcher, stepping, binary, scene) raise these and know
nothing of HTTP or websockets; ``error_mapping.py`` is the one place that turns each kind into an
HTTP status with an ``ErrorBody``, or a websocket error message and close code.

Every error has a machine-readable ``code`` (the ``error`` of the body: ``wrong_length``,
``unknown_session``...) and a readable message; errors about an input also name the ``field`` and
what was ``expected`` and ``got``.
"""

from __future__ import annotations

from typing import Any, ClassVar


class EmulatorError(Exception):
    """The base of every domain error; ``code`` defaults to the class's own."""

    default_code: ClassVar[str] = "error"

    def __init__(
        self,
        message: str,
        *,
        code: str | None = None,
        field: str | None = None,
        expected: Any = None,
        got: Any = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        self.code = code or self.default_code
        self.field = field
        self.expected = expected
        self.got = got


class BadInput(EmulatorError):
    """A request or message that cannot be served as it is (wrong length, not finite, malformed...)."""

    default_code = "invalid_request"


class UnknownSession(EmulatorError):
    """No such session: never created, deleted, expired, or owned by another API key."""

    default_code = "unknown_session"

    @classmethod
    def named(cls, sid: str) -> UnknownSession:
        return cls(f"no session {sid!r} (never created, deleted or expired)")


class UnknownModel(EmulatorError):
    """No such model (``unknown_model``) or no such version of it (``unknown_version``)."""

    default_code = "unknown_model"


class UnknownPolicy(EmulatorError):
    """No such policy (or version of it) for the model."""

    default_code = "unknown_policy"


class PolicyMismatch(EmulatorError):
    """A policy asked to drive a session of an emulator version it was not trained through."""

    default_code = "policy_emulator_mismatch"


class Diverged(EmulatorError):
    """The session's emulator produced a non-finite state; the session is kept at its last finite one."""

    default_code = "diverged"

    @classmethod
    def at_step(cls, sid: str, step: int) -> Diverged:
        return cls(
            f"session {sid!r} diverged: its step {step} produced a non-finite state; "
            "its last finite state is kept, create a new session to continue"
        )


class WrongMode(EmulatorError):
    """A message that the connection's current mode does not take."""

    default_code = "wrong_mode"


class QuotaExceeded(EmulatorError):
    """Too many sessions: in this replica (``too_many_sessions``) or for one API key; ``field`` names the
    limit (``MAX_SESSIONS``, ``MAX_SESSIONS_PER_KEY``)."""

    default_code = "too_many_sessions"


class TooLarge(EmulatorError):
    """A batch (``batch_too_large``) or body (``body_too_large``) over its configured cap."""

    default_code = "batch_too_large"


class UnsupportedMediaType(EmulatorError):
    default_code = "unsupported_media_type"


class ClientDisconnected(EmulatorError):
    """The client went away before its request was read."""

    default_code = "client_disconnected"


class StepFailed(EmulatorError):
    """The emulator's step itself failed (an ONNX Runtime error): a fault of the service."""

    default_code = "step_failed"
