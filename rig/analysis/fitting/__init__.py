"""The fitting engine: bounded least squares in the record's own scales (`scaling`), variable
projection for models linear in all but one parameter (`separable`, `contact_fit`, `lean`),
and the fit with its result and report (`fit`).

Imports from `stats` and `trials`.
"""
