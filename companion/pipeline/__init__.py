"""The safe-landing-zone pipeline, steps 1-5 of docs/design.md: density, occupancy, head-plane
grid, proposals, tracking. Pure: numpy arrays in and out, no I/O beyond loading the model file."""
