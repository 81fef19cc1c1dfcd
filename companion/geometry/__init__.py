"""Pure geometry shared by every layer: the camera model and poses (``camera``), and the
conversion between geodetic coordinates and local NED metres (``geodesy``). No I/O."""
