"""Test-wide settings: reproducible, deadline-free property tests (CI machines are slow)."""

from hypothesis import HealthCheck, settings

settings.register_profile(
    "slipmap",
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("slipmap")
