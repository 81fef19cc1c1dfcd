"""What flights are evidence of.

``results``: the rows a flight writes, the results file, their summary and confidence bounds (the
bottom of ``sim``: flights write it). Above the flights: ``compare`` (``companion sim-compare``),
``strikes`` and ``person_halo`` (``python -m sim.evidence.strikes`` / ``.person_halo``),
``false_positives`` and ``walker_alarms``.
"""
