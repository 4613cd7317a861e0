"""One router per concern: status/health/metrics/frame, settings, session control."""
