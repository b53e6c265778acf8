"""The controller API's routers: ``jobs`` (REST), ``events`` (SSE and websocket), ``tasks``, ``policies``
(policy jobs' submission, stored policies, policy tasks) and ``policy_jobs``."""
