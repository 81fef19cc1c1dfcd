"""MAVLink side of the service: the link, vehicle state, failsafe triggers and autopilot flavours.

- ``link``: ``MavLink`` (transport, heartbeat, message intervals, commands, subscribers, counters).
- ``state``: ``VehicleState`` (telemetry with receive times, ``pose_at(t)``, ``is_fresh``).
- ``failsafe``: ``FailsafeMonitor`` turns telemetry, a GCS command or a local request into a ``Trigger``.
- ``autopilot`` / ``ardupilot`` / ``px4``: how to fly to a point, land, hold and hand back.
- ``statustext``: ``send_statustext`` for human-readable events on the ground station.
"""
