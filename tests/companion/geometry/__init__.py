"""Tests of companion.geometry: the camera model."""
