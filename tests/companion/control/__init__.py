"""Tests of companion.control: the landing decision."""
