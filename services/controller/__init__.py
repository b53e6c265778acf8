"""Controller service: BPTT controller-synthesis jobs through a Redis (RQ) job queue.

``app.py`` is the HTTP API (submit, watch, cancel, fetch results); ``worker.py`` runs jobs, one forked
process per job. Neither the API nor a worker's parent process imports PyTorch: only the forked job
process does (``jobs.py``), so a worker never forks after torch has started its thread pools.
"""
