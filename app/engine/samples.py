"""Measurement arrays the engine consumes, one dataclass per kind.

The service turns JSON samples into these (ids already mapped to indices into
the site's tables) so that no algorithm touches strings or dicts. Times are
int64 milliseconds of measurement time; absent IMU fields are NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_EMPTY: dict[tuple[tuple[int, ...], type], np.ndarray] = {}


def _empty(shape: tuple[int, ...] = (0,), dtype: type = float) -> np.ndarray:
    """Return an empty array of ``shape`` and ``dtype``, one shared per kind.

    Samples of an absent kind are the default of every batch and window a
    worker handles; an array with no elements holds nothing to share, and
    making a new one each time cost two dozen allocations a device a window.
    """
    empty = _EMPTY.get((shape, dtype))
    if empty is None:
        empty = _EMPTY[(shape, dtype)] = np.zeros(shape, dtype=dtype)
    return empty


@dataclass
class RssiReadings:
    """Received signal strengths of known transmitters (WiFi, BLE) heard by the device.

    ``tx`` indexes ``SiteModel.transmitters``; readings of unknown ids are
    dropped (and counted) before they get here.
    """

    t: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int64))
    tx: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int32))
    rssi: np.ndarray = field(default_factory=_empty)

    def __len__(self) -> int:
        """Return the number of readings."""
        return int(self.t.size)


@dataclass
class Sightings:
    """Signal strengths of a tag as heard by fixed locators (locator mode).

    ``locator`` indexes ``SiteModel.locators``: here the receiver is the fixed
    point and the tag the unknown, the reverse of :class:`RssiReadings`.
    """

    t: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int64))
    locator: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int32))
    rssi: np.ndarray = field(default_factory=_empty)

    def __len__(self) -> int:
        """Return the number of sightings."""
        return int(self.t.size)


@dataclass
class ImuSamples:
    """Inertial samples: acc (m/s²), gyro (rad/s), mag (µT), Android rotation vector."""

    t: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int64))
    acc: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    gyro: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    mag: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    rot: np.ndarray = field(default_factory=lambda: _empty((0, 4)))

    def __len__(self) -> int:
        """Return the number of samples."""
        return int(self.t.size)


@dataclass
class Ranges:
    """UWB two-way ranges (m) to anchors indexed into ``SiteModel.anchors``."""

    t: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int64))
    anchor: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int32))
    range: np.ndarray = field(default_factory=_empty)
    std: np.ndarray = field(default_factory=_empty)

    def __len__(self) -> int:
        """Return the number of ranges."""
        return int(self.t.size)


@dataclass
class Fixes:
    """Position fixes computed elsewhere (e.g. a UWB gateway): x, y, z (m), floor index."""

    t: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int64))
    xyz: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    floor: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int32))
    std: np.ndarray = field(default_factory=_empty)

    def __len__(self) -> int:
        """Return the number of fixes."""
        return int(self.t.size)


@dataclass
class Pressure:
    """Barometer readings (hPa)."""

    t: np.ndarray = field(default_factory=lambda: _empty(dtype=np.int64))
    hpa: np.ndarray = field(default_factory=_empty)

    def __len__(self) -> int:
        """Return the number of samples."""
        return int(self.t.size)


@dataclass
class Batch:
    """Everything one device reported in one window of measurement time."""

    rssi: RssiReadings = field(default_factory=RssiReadings)
    sightings: Sightings = field(default_factory=Sightings)
    imu: ImuSamples = field(default_factory=ImuSamples)
    ranges: Ranges = field(default_factory=Ranges)
    fixes: Fixes = field(default_factory=Fixes)
    pressure: Pressure = field(default_factory=Pressure)

    def __len__(self) -> int:
        """Return the number of samples of every kind together."""
        return (
            len(self.rssi)
            + len(self.sightings)
            + len(self.imu)
            + len(self.ranges)
            + len(self.fixes)
            + len(self.pressure)
        )


@dataclass(frozen=True)
class Estimate:
    """One position the engine emits.

    ``floor`` indexes ``SiteModel.floors``; ``heading`` is degrees clockwise
    from +y in [0, 360) or NaN when unknown; ``accuracy`` is the radius (m)
    holding the true position with 68% probability. ``odometry`` is where the
    device's own steps alone have taken it (m, site frame, origin where its
    filter started), for a smoother to weigh positions against its motion;
    None from filters that count no steps. ``smoothed`` marks a position
    re-emitted refined by the positions after it.
    """

    t: int
    x: float
    y: float
    z: float
    floor: int
    heading: float
    accuracy: float
    speed: float
    method: str
    odometry: tuple[float, float] | None = None
    smoothed: bool = False
