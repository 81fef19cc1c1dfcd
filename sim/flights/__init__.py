"""Flights: the simulated vehicle and world flown with the real service.

From the bottom: ``results`` (the rows a flight writes, the results file, their summary and
confidence bounds), ``spec`` (what to fly, how it ended, the service's command line),
``inprocess`` (the service in the flight's own process), ``flight`` (one closed-loop flight,
judged on the truth), ``lockstep`` (a flight on the simulated clock, in a process of its own), and
the commands: ``scenarios`` (``companion sim-scenarios``), ``demo`` (``companion demo``) and
``standalone`` (``companion sim``).
"""
