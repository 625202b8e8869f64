"""Measurement arrays the engine consumes, one dataclass per kind.

The service turns JSON samples into these (ids already mapped to indices into
the site's tables) so that no algorithm touches strings or dicts. Times are
int64 milliseconds of measurement time; absent IMU fields are NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _shared_empty(shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """Return a read-only empty array: one of each kind is shared by every absent sample kind.

    Samples of an absent kind are the default of every batch and window a
    worker handles; an array with no elements holds nothing to share, and
    making a new one each time cost two dozen allocations a device a window.
    """
    empty: np.ndarray = np.zeros(shape, dtype=dtype)
    empty.flags.writeable = False
    return empty


_TIMES = _shared_empty((0,), np.int64)
_INDICES = _shared_empty((0,), np.int32)
_VALUES = _shared_empty((0,), float)
_VECTORS = _shared_empty((0, 3), float)
_QUATERNIONS = _shared_empty((0, 4), float)


def no_times() -> np.ndarray:
    """Return the shared empty array of times (ms)."""
    return _TIMES


def no_indices() -> np.ndarray:
    """Return the shared empty array of table indices."""
    return _INDICES


def no_values() -> np.ndarray:
    """Return the shared empty array of values."""
    return _VALUES


def no_vectors() -> np.ndarray:
    """Return the shared empty array of 3-vectors."""
    return _VECTORS


def no_quaternions() -> np.ndarray:
    """Return the shared empty array of quaternions."""
    return _QUATERNIONS


@dataclass
class RssiReadings:
    """Received signal strengths of known transmitters (WiFi, BLE) heard by the device.

    ``tx`` indexes ``SiteModel.transmitters``; readings of unknown ids are
    dropped (and counted) before they get here.
    """

    t: np.ndarray = field(default_factory=no_times)
    tx: np.ndarray = field(default_factory=no_indices)
    rssi: np.ndarray = field(default_factory=no_values)

    def __len__(self) -> int:
        """Return the number of readings."""
        return int(self.t.size)


@dataclass
class Sightings:
    """Signal strengths of a tag as heard by fixed locators (locator mode).

    ``locator`` indexes ``SiteModel.locators``: here the receiver is the fixed
    point and the tag the unknown, the reverse of :class:`RssiReadings`.
    """

    t: np.ndarray = field(default_factory=no_times)
    locator: np.ndarray = field(default_factory=no_indices)
    rssi: np.ndarray = field(default_factory=no_values)

    def __len__(self) -> int:
        """Return the number of sightings."""
        return int(self.t.size)


@dataclass
class ImuSamples:
    """Inertial samples: acc (m/s²), gyro (rad/s), mag (µT), Android rotation vector."""

    t: np.ndarray = field(default_factory=no_times)
    acc: np.ndarray = field(default_factory=no_vectors)
    gyro: np.ndarray = field(default_factory=no_vectors)
    mag: np.ndarray = field(default_factory=no_vectors)
    rot: np.ndarray = field(default_factory=no_quaternions)

    def __len__(self) -> int:
        """Return the number of samples."""
        return int(self.t.size)


@dataclass
class Ranges:
    """UWB two-way ranges (m) to anchors indexed into ``SiteModel.anchors``."""

    t: np.ndarray = field(default_factory=no_times)
    anchor: np.ndarray = field(default_factory=no_indices)
    range: np.ndarray = field(default_factory=no_values)
    std: np.ndarray = field(default_factory=no_values)

    def __len__(self) -> int:
        """Return the number of ranges."""
        return int(self.t.size)


@dataclass
class Fixes:
    """Position fixes computed elsewhere (e.g. a UWB gateway): x, y, z (m), floor index."""

    t: np.ndarray = field(default_factory=no_times)
    xyz: np.ndarray = field(default_factory=no_vectors)
    floor: np.ndarray = field(default_factory=no_indices)
    std: np.ndarray = field(default_factory=no_values)

    def __len__(self) -> int:
        """Return the number of fixes."""
        return int(self.t.size)


@dataclass
class Pressure:
    """Barometer readings (hPa)."""

    t: np.ndarray = field(default_factory=no_times)
    hpa: np.ndarray = field(default_factory=no_values)

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
