"""Tests of companion.replay: the pipeline offline over recordings."""
