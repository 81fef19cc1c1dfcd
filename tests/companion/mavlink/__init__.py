"""Tests of companion.mavlink: the link, the autopilot adapters, the vehicle state."""
