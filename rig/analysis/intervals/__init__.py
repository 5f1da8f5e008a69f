"""How far a fitted number can move, beyond its standard error: profile-likelihood intervals
(`profile`), a parametric bootstrap through the whole pipeline (`bootstrap`), and the
systematic error over the choices of the fit's range and baseline (`systematic`).

Imports from `stats`, `trials` and `fitting`.
"""
