"""What flights are evidence of: analyses over flights and their results files.

``compare`` (``companion sim-compare``: two results files seed by seed, with exact tests),
``strikes`` and ``person_halo`` (``python -m sim.evidence.strikes`` / ``.person_halo``),
``false_positives`` and ``walker_alarms``. The rows themselves, their summary and bounds are
``sim.flights.results``, below: flights write them.
"""
