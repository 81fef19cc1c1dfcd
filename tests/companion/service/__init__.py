"""Tests of companion.service: the daemon's parts (runner, camera sources, status page, health)."""
