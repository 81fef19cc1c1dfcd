"""The simulator: a multicopter that speaks MAVLink like ArduPilot Copter or PX4, its world, the
flights it flies with the real service, and what those flights are evidence of.

Packages by job; each imports only those below it (pyproject.toml's import contracts):

- ``sim.commands``: the simulator's ``companion`` subcommands, routed by entry points;
- ``sim.evidence``: analyses of flights and their results (``compare``, ``strikes``,
  ``person_halo``, ``false_positives``, ``walker_alarms``);
- ``sim.flights``: what a flight flies and how it ended (``spec``), the rows and their summary
  (``results``), one closed-loop flight (``flight``), on the simulated clock (``lockstep``,
  ``inprocess``), many of them (``scenarios``), the demo (``demo``) and ``companion sim``
  (``standalone``);
- ``sim.world``: the people, the ground, the render and the camera server;
- ``sim.vehicle``: the kinematic vehicle, the autopilot and its flavours, MAVLink links, routing,
  faults and ``Simulator`` composing them in real time. No dependency on ``companion.mavlink``:
  an independent peer on pymavlink's codec.

``sim.world`` and ``sim.vehicle`` are independent of each other: a flight joins them.
"""
