"""Rig models, one module per instrument (the ``--rig`` names: :mod:`gyrojax.rigs`)."""

from ._base import AbstractRig as AbstractRig
from .esg import ESGConditions as ESGConditions
from .esg import ESGRig as ESGRig
from .gyrotheodolite import GyrotheodoliteConditions as GyrotheodoliteConditions
from .gyrotheodolite import GyrotheodoliteRig as GyrotheodoliteRig
from .imu import IMUConditions as IMUConditions
from .imu import IMURig as IMURig
from .platform import PlatformConditions as PlatformConditions
from .platform import PlatformRig as PlatformRig
from .schuler import SchulerConditions as SchulerConditions
from .schuler import SchulerRig as SchulerRig
