"""Every table, imported in one place so metadata and Alembic see them all."""

from app.core.db import Base
from app.devices.models import DeviceState
from app.floors.models import Floor
from app.keys.models import ApiKey
from app.positions.models import Position
from app.radiomaps.models import CalibratedTransmitter, RadioMapBuild, RadioMapFloor, RadioMapJob
from app.sites.models import Site
from app.surveys.models import Survey
from app.tracks.models import Track

__all__ = [
    "ApiKey",
    "Base",
    "CalibratedTransmitter",
    "DeviceState",
    "Floor",
    "Position",
    "RadioMapBuild",
    "RadioMapFloor",
    "RadioMapJob",
    "Site",
    "Survey",
    "Track",
]
