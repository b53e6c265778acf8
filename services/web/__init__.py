"""The dashboard's static server: ``web/dist`` plus ``/config.json`` (where the services are)."""
