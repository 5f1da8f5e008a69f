"""One `rig analyze` request carried out (`session`): its records read and prepared (`inputs`),
what a fit says as JSON and beside its report (`results`), the named models compared (`compare`),
and its figures and report.md (`report`).

Imports from every subpackage below it; only `batch` sits above.
"""
