"""The simulator: a multicopter that speaks MAVLink like ArduPilot Copter or PX4, and its world.

Vehicle side (no dependency on ``companion.mavlink``: an independent peer on pymavlink's codec):
``sim.vehicle`` kinematics, ``sim.autopilot`` / ``sim.ardupilot`` / ``sim.px4`` flight modes and
MAVLink behaviour, ``sim.endpoint`` UDP links, ``sim.faults`` failsafe kinds and link faults,
``sim.simulator.Simulator`` composing them in real time, ``sim.cli`` for ``companion sim``.
"""
