"""Tests of the simulator's parts that fly nothing (flights are in tests/flights), one folder per package of sim/."""
