"""The local web page of `kbbatch review` (server in app.py, page in static/)."""
