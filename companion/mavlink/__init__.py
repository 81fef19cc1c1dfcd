"""MAVLink side of the service: the link, vehicle state, failsafe triggers and autopilot flavours.

- ``link``: ``MavLink`` (transport, heartbeat, message intervals, commands, subscribers, counters).
- ``state``: ``VehicleState`` (telemetry placed at the autopilot's sample time, ``pose_at(t)``,
  ``covers(t)``, ``is_fresh``).
- ``clock`` / ``timesync``: ``AutopilotClock`` maps ``time_boot_ms`` onto our clock (TIMESYNC where
  answered) and refuses late or backwards samples.
- ``transports``: UDP (peers pinned by address), TCP, serial; ``keygen``: ``companion signing-key``.
- ``failsafe``: ``FailsafeMonitor`` turns telemetry, a GCS command or a local request into a ``Trigger``.
- ``autopilot`` / ``ardupilot`` / ``px4``: how to fly to a point, land, hold and hand back.
- ``statustext``: ``send_statustext`` for human-readable events on the ground station.
"""
