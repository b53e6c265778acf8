"""The controller API's routers: ``jobs`` (REST), ``events`` (SSE and websocket), ``tasks``."""
