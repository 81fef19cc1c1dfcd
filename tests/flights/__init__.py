"""Every test that flies the simulator over MAVLink, or starts a simulator or a flight: the slow lane (.ci/tests)."""
