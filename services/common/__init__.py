"""What the services share: API-key auth (``auth``), the error type and its JSON form (``errors``),
JSON-line logs (``logs``), the settings every service has (``settings``) and the uvicorn entry point
(``server``).

Nothing is imported here, so a service takes only the modules it uses: the dashboard's image has
``logs``, ``settings`` and ``server`` but not ``neuroanimator`` (which ``auth`` and ``errors`` need
for the wire type ``ErrorBody``).
"""
