"""Tests of sim.evidence: comparisons, strikes and the other analyses."""
