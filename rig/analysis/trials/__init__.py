"""Trials for analysis: a record of any kind on a uniform time grid, with its contact, direction
of loading, baseline, phases and the record's own scales (`data`); where its contact starts and
ends (`contact`); its velocity and phases (`motion`).

Imports from `rig.analysis.stats` only.
"""
