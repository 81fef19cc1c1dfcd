"""Tests of sim.flights that fly nothing: the scenario runner's bookkeeping, the demo's output."""
