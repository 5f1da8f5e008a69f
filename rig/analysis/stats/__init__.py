"""The noise and what is judged against it: the sensor's noise model, standard errors under
correlated residuals, the one criterion (BIC on the effective sample count), the adequacy tests,
and the small numerical helpers they share (a straight line, Gaussian draws).

The lowest layer of the analysis: it imports nothing else from `rig.analysis`.
"""
