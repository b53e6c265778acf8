"""``/ws/sessions/{id}``: lock-step and real-time modes, JSON and binary frames.

The package: ``transport.py`` (the socket on raw ASGI, sending, the latest-state-wins queue),
``protocol.py`` (client messages parsed, server messages encoded), ``connection.py`` (one client: its
settings and lock-step mode), ``realtime.py`` (real-time mode's ticker and pusher), ``route.py`` (the
ASGI route: handshake to close). Every step goes through the stepping core (``stepping.py``), every
error through ``error_mapping.py``.

Lock-step (the default): ``{"type": "step", "controls": [...], "forces": [...], "seq": n}`` (or a
binary frame, proto/frames.md) → the next state. Real-time (``{"type": "start", "mode": "realtime"}``
or ``?mode=realtime``): the server advances the session every Δt of wall time (the model's super
timestep × ``WS_REALTIME_SCALE``) with the latest inputs the client sent (``{"type": "controls", ...}``
or binary frames) and pushes each new state. ``format=binary`` (in ``start`` or the query) sends
states as binary frames; errors are always JSON text. ``{"type": "ping"}`` → ``pong``.

For drawing (JSON format only): ``poses: true`` (in ``start`` or the query) adds every body's world
pose to each state; ``shadow: true`` runs a MuJoCo shadow of the session, stepped with the same
held inputs, whose state (and poses) come along in each state message (``scene.MujocoShadow``).

A client's outgoing states go through its own latest-state-wins queue of ``WS_QUEUE_SIZE`` (1–2)
frames, drained by its own task, so a slow reader only loses intermediate states: the ticker, the
batcher and every other client keep going. Every send has a timeout (``WS_SEND_TIMEOUT_S``); a send
that times out ends the connection, as does the server's websocket ping going unanswered (uvicorn's
``--ws-ping-interval`` / ``--ws-ping-timeout``, 20 s each by default), so a client that vanishes
without closing is noticed. The session itself is kept until its TTL.

A malformed message gets ``{"type": "error", ...}`` (the connection stays open); an unknown session
gets an error and close code 4404; a bad ``mode``/``format`` query gets an error and close code 4422.
"""

from services.emulator.ws.route import SessionSocketRoute

__all__ = ["SessionSocketRoute"]
