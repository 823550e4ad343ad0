"""Fitting a cell model to logged flights, and judging the fit on data it has not seen.

- :mod:`~packpilot.model.fit.profile` — a battery stepped over a logged profile;
- :mod:`~packpilot.model.fit.fit` — bounded least squares with uncertainty and flags;
- :mod:`~packpilot.model.fit.validate` — fit on the first part, test on the rest, verdict;
- :mod:`~packpilot.model.fit.cellset` — the fitted set as a cell parameter file;
- :mod:`~packpilot.model.fit.synthetic` — logs made by the plant from known parameters.
"""
