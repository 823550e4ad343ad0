"""State-of-charge estimation: coulomb counting corrected from the OCV after a rest."""

from packpilot.config.soc import SocConfig
from packpilot.control.soc.controller import METHOD, SocEstimator

__all__ = ["METHOD", "SocConfig", "SocEstimator"]
