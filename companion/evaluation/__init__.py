"""Measuring density models on the crowd data sets (``companion eval``)."""
