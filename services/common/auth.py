"""API keys: when ``API_KEYS`` is set, every call but ``/healthz``, ``/readyz`` and ``/metrics`` needs one.

A key is sent as ``Authorization: Bearer <key>`` or ``X-API-Key: <key>`` (websockets and event streams
may also use the ``?api_key=<key>`` query parameter, since browsers cannot set headers on them). A
missing or wrong key gets 401 (a websocket handshake is denied with 401, or closed with code 4401 where the server cannot
send a denial response).

The caller is known for the rest of the request through the ``CALLER`` context variable, set by
``ApiKeyMiddleware`` (a pure ASGI middleware, so the value reaches the endpoint and every task it
starts). It holds the key's *id*, never the key: that id owns what the key creates (the emulator's
sessions, the controller's jobs), and is what is stored with them in Redis and written in logs. An id
is ``k-`` + 16 hex digits of the key's HMAC-SHA256 under the server secret ``API_KEY_SECRET``, so that
an id read from a checkpoint or a log cannot be turned back into a short key by trying keys offline.
Without ``API_KEY_SECRET`` a service draws a random secret at start: ids then change at each restart
(restored sessions and earlier jobs lose their owners), which it warns about. ``OwnerDep`` is the
owner as a FastAPI dependency, ``public`` while keys are off.

``OPERATOR_KEYS`` are API keys with an operator's rights (they need not be repeated in ``API_KEYS``):
``OPERATOR`` says, for the rest of the request, that the caller holds one. An operator sees every
uploaded model, and publishes and deletes them (``services.common.tenancy``).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import secrets
from contextvars import ContextVar
from typing import Annotated

from fastapi import Depends
from starlette.requests import HTTPConnection
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.websockets import WebSocket

from neuroanimator.contracts.emulator import ErrorBody
from services.common.settings import ApiSettings

log = logging.getLogger(__name__)

OPEN_PATHS = frozenset({"/healthz", "/readyz", "/metrics"})
CALLER: ContextVar[str | None] = ContextVar("caller", default=None)
"""The key id of the current request's caller; None when auth is off (or outside a request)."""
OPERATOR: ContextVar[bool] = ContextVar("operator", default=False)
"""Whether the current request's caller holds an operator key (``OPERATOR_KEYS``)."""
PUBLIC = "public"
"""The owner of what is made while API keys are off (``OwnerDep``)."""


def key_id(key: str, secret: bytes) -> str:
    """The id of a key under the server secret: what owns what the key creates and is stored with it
    (never the key itself); a keyed hash, so that it cannot be checked against guessed keys offline."""
    return "k-" + hmac.new(secret, key.encode(), hashlib.sha256).hexdigest()[:16]


def _split(spec: str) -> set[str]:
    return {k.strip() for k in spec.split(",") if k.strip()}


class ApiKeys:
    """The configured keys, from the comma-separated ``API_KEYS`` and ``OPERATOR_KEYS`` (blanks around
    keys are ignored), and the secret of their ids (``API_KEY_SECRET``; a random one when it is empty)."""

    def __init__(self, spec: str, secret: str = "", operators: str = "") -> None:
        ops = _split(operators)
        keys = _split(spec) | ops
        self.secret_given = bool(secret)
        self._secret = secret.encode() if secret else secrets.token_bytes(32)
        self._ids = {hashlib.sha256(k.encode()).digest(): key_id(k, self._secret) for k in keys}
        self.operators = frozenset(key_id(k, self._secret) for k in ops)
        if keys and not secret:
            log.warning(
                "API_KEY_SECRET is not set: the ids of API keys (the owners of sessions and jobs) are "
                "drawn afresh at each start, so what a restart restores loses its owner; set it"
            )

    @classmethod
    def of(cls, settings: ApiSettings) -> ApiKeys:
        """The keys of a service's settings (``API_KEYS``, ``API_KEY_SECRET``, ``OPERATOR_KEYS``)."""
        return cls(settings.api_keys, settings.api_key_secret, settings.operator_keys)

    def id_of(self, key: str) -> str:
        """The id ``key`` has here (configured or not)."""
        return key_id(key, self._secret)

    @property
    def enabled(self) -> bool:
        return bool(self._ids)

    def __len__(self) -> int:
        return len(self._ids)

    def owner(self, key: str | None) -> str | None:
        """The key id of a configured key, else None (looked up by digest, not by comparing keys)."""
        if not key:
            return None
        return self._ids.get(hashlib.sha256(key.encode()).digest())


def presented_key(conn: HTTPConnection) -> str | None:
    """The key a request carries: Authorization Bearer, X-API-Key, or (websockets and event streams,
    ``.../events``) ``?api_key=``."""
    auth = conn.headers.get("authorization", "")
    scheme, _, value = auth.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    if conn.headers.get("x-api-key"):
        return conn.headers["x-api-key"].strip()
    # browsers cannot give websockets or EventSource (server-sent events) headers
    if conn.scope["type"] == "websocket" or conn.scope["path"].endswith("/events"):
        return conn.query_params.get("api_key") or None
    return None


class ApiKeyMiddleware:
    """Rejects calls without a valid key (401) and sets ``CALLER`` for the ones with one."""

    def __init__(self, app: ASGIApp, keys: ApiKeys) -> None:
        self.app = app
        self.keys = keys

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or scope["path"] in OPEN_PATHS:
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        key = presented_key(conn)
        owner = self.keys.owner(key)
        if owner is None:
            await self._deny(scope, receive, send, missing=key is None)
            return
        token = CALLER.set(owner)
        operator = OPERATOR.set(owner in self.keys.operators)
        try:
            await self.app(scope, receive, send)
        finally:
            OPERATOR.reset(operator)
            CALLER.reset(token)

    async def _deny(self, scope: Scope, receive: Receive, send: Send, missing: bool) -> None:
        how = "'Authorization: Bearer <key>' or 'X-API-Key: <key>'"
        if scope["type"] == "websocket":
            how += " (or the query parameter ?api_key=<key>)"
        if missing:
            body = ErrorBody(error="unauthorized", message=f"this service needs an API key: send {how}")
        else:
            body = ErrorBody(
                error="invalid_api_key", message=f"the API key is not valid; send a key with {how}"
            )
        log.info("call denied", extra={"path": scope["path"], "reason": body.error})
        response = JSONResponse(body.model_dump(), status_code=401, headers={"WWW-Authenticate": "Bearer"})
        if scope["type"] == "http":
            await response(scope, receive, send)
            return
        ws = WebSocket(scope, receive, send)
        if "websocket.http.response" in scope.get("extensions", {}):
            await ws.send_denial_response(response)
        else:
            await ws.close(code=4401, reason=body.message[:120])


# async: FastAPI runs a plain ``def`` dependency in a worker thread, a thread hop per request.
async def get_owner() -> str:
    """The caller's key id (set by ``ApiKeyMiddleware``), or ``public`` when keys are off."""
    return CALLER.get() or PUBLIC


OwnerDep = Annotated[str, Depends(get_owner)]
