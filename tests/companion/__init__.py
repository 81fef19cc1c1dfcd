"""Tests of the companion service, one folder per package of companion/."""
