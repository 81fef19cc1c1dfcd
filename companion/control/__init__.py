"""Landing control: the zone planner, the landing state machine and its async runner; geodesy."""
