"""Tests of companion.evaluation: measuring density models."""
