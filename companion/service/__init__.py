"""The companion daemon: configuration, camera, asyncio wiring, systemd notify, flight recorder."""
