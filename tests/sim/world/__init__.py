"""Tests of sim.world: people, ground, render, the camera server."""
