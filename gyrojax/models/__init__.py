"""Rig models, one module per instrument; ``RIGS`` maps ``--rig`` names to constructors."""

from ._base import AbstractRig as AbstractRig
from .esg import ESGConditions as ESGConditions
from .esg import ESGRig as ESGRig

RIGS = {"esg": ESGRig}
