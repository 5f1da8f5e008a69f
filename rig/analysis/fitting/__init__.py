"""The fitting engine: bounded least squares in the record's own scales (`scaling`), variable
projection for models linear in all but one parameter (`separable`, `contact_fit`, `lean`), the
fit with its covariance (`fit`), and what it found, its report and its plain data (`result`).

Imports from `stats` and `trials`.
"""
