"""Every table, imported in one place so metadata and Alembic see them all."""

from app.analytics.models import ZoneEventRecord
from app.core.db import Base
from app.devices.models import Device, DeviceStateRecord
from app.floors.models import FloorRecord
from app.keys.models import ApiKey
from app.outputs.models import OutboxRow, Output
from app.positions.models import PositionRecord
from app.radiomaps.models import (
    CalibratedTransmitter,
    RadioMapBuild,
    RadioMapFloor,
    RadioMapJob,
    SurveyGuidanceFloor,
)
from app.sites.models import Site
from app.surveys.models import SurveyRecord
from app.tracks.models import Track

__all__ = [
    "ApiKey",
    "Base",
    "CalibratedTransmitter",
    "Device",
    "DeviceStateRecord",
    "FloorRecord",
    "OutboxRow",
    "Output",
    "PositionRecord",
    "RadioMapBuild",
    "RadioMapFloor",
    "RadioMapJob",
    "Site",
    "SurveyGuidanceFloor",
    "SurveyRecord",
    "Track",
    "ZoneEventRecord",
]
