import os

from hypothesis import HealthCheck, settings

# Two cores: keep example counts modest; CI gets the same profile.
settings.register_profile(
    "default", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))
