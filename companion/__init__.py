"""companion: a companion-computer service that lands a drone away from people.

The per-frame pipeline (``companion.pipeline``) follows González-Trejo et al., "On the
Visual-based Safe Landing of UAVs in Populated Areas": density map -> occupancy map -> head-plane
grid -> largest free circles -> Kalman-tracked landing zones.
"""

__version__ = "0.1.0"
