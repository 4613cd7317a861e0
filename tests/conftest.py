"""Suite-wide settings: property tests are judged on what the code returns, never on how fast a
loaded machine ran one example (hypothesis's 200-ms deadline and its too-slow health check are
wall-clock checks; a CPU hog beside the suite tripped neither only by luck)."""

from __future__ import annotations

from hypothesis import HealthCheck, settings

settings.register_profile("dpmhw", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("dpmhw")
