"""The trainer API's routers: ``trainings`` (uploads, progress, events, cancel) and ``models`` (uploaded models)."""
