"""Tests of sim.vehicle: kinematics and the autopilot, without MAVLink."""
