"""The test suite: folders mirror companion/ and sim/; every flight is in tests/flights."""
