"""The FastAPI service: status, settings, session control."""
