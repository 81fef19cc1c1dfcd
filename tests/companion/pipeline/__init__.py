"""Tests of companion.pipeline: density, occupancy, proposals, tracks, the risk map."""
