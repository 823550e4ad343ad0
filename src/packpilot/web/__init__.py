"""PackPilot."""
