"""Flights: the simulated vehicle and world flown with the real service.

``spec`` (what to fly, how it ended, the service's command line), ``inprocess`` (the service in
the flight's own process), ``flight`` (one closed-loop flight, judged on the truth), ``lockstep``
(a flight on the simulated clock, in a process of its own), ``scenarios`` (``companion
sim-scenarios``), ``demo`` (``companion demo``) and ``standalone`` (``companion sim``).
"""
