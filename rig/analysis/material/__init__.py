"""A fit in the material's own terms: the apparent modulus against depth (`modulus`) and the
creep form, its miss as a length and the creep compliance (`creep`).

Imports from `stats`, `trials` and `fitting`.
"""
