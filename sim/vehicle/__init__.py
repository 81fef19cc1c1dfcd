"""The simulated vehicle: kinematics (``kinematics``), the autopilot (``autopilot``) and its
flavours (``ardupilot``, ``px4``), MAVLink over UDP (``endpoint``), forwarding between links
(``routing``), failsafes and link faults (``faults``), and ``simulator.Simulator`` composing them
in real time. Knows nothing of the world it flies over (anything with ``step(dt)``).
"""
