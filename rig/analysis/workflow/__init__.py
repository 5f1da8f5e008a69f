"""One `rig analyze` request carried out (`session`): its inputs and JSON (`analyze`), and its
figures and report.md (`report`).

Imports from every subpackage below it; only `batch` sits above.
"""
