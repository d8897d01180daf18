"""Log readers and writers: ROS bags, CARMEN logs, relations files, maps, trajectories.

:func:`read_log` picks the reader from the file; the readers themselves are
:func:`read_rosbag` and :func:`read_carmen` (:func:`write_carmen` writes any evenly spaced
log as CARMEN). Every reader returns a
:class:`~jaxslam.laserlog.LaserLog` and raises :class:`~jaxslam.laserlog.LogError`
naming the file and the line or message for malformed input.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from jaxslam.io.carmen import ONLY_COMMENTS, read_carmen, text_problem, write_carmen
from jaxslam.io.maps import read_map, write_map
from jaxslam.io.relations import Relations, read_relations, sideways_relations
from jaxslam.io.rosbag import read_rosbag
from jaxslam.io.trajectory import read_trajectory, write_trajectory
from jaxslam.laserlog import LaserLog, LogError

__all__ = [
    "LogError",
    "Relations",
    "read_carmen",
    "read_log",
    "read_map",
    "read_relations",
    "read_rosbag",
    "read_trajectory",
    "sideways_relations",
    "write_carmen",
    "write_map",
    "write_trajectory",
]

_CARMEN_DATA = ("FLASER", "ROBOTLASER1", "ODOM")
# A CARMEN message name: PARAM, SYNC, RAWLASER1, TRUEPOS, ... (upper case, digits, underscores).
_CARMEN_NAME = re.compile(rb"^[A-Z][A-Z0-9_]*$")
# How far into a text file to look for the first laser or odometry line (PARAM blocks can be long).
_SNIFF_BYTES = 1 << 20
_EXPECTED = "a ROS 1 '.bag' file, a ROS 2 bag folder (with metadata.yaml) or a CARMEN text log"


def read_log(path, **kwargs) -> LaserLog:
    """Read a laser log with the reader its file calls for.

    A ``.bag`` file or a folder holding ``metadata.yaml`` goes to :func:`read_rosbag`; a
    text file whose first non-comment lines are CARMEN messages, the first data one
    ``FLASER``, ``ROBOTLASER1`` or ``ODOM`` (PARAM, SYNC, ... lines may come first), goes
    to :func:`read_carmen`. ``kwargs`` are passed on to that reader: for a bag
    ``scan_topic``, ``odom_topic``, ``odom_frame``, ``base_frame``, ``laser_pose`` and
    ``max_scans``; for a CARMEN log ``range_max``, ``odometry_source`` and ``laser_pose``.

    Returns:
        The :class:`~jaxslam.laserlog.LaserLog` of the reader.

    Raises:
        LogError: the path does not exist or is none of those kinds (the message names the
            path and what was expected), an option that the file's reader does not take (named
            by its ``jaxslam map`` flag), or the reader's own errors.
    """
    src = os.fspath(path)
    target = Path(src)
    if not target.exists():
        raise LogError(f"{src}: no such file or folder; expected {_EXPECTED}")
    if target.is_dir():
        if (target / "metadata.yaml").is_file():
            _check_kwargs(src, kwargs, _BAG_OPTIONS, "a bag")
            return read_rosbag(target, **kwargs)
        raise LogError(f"{src}: a folder without metadata.yaml; expected {_EXPECTED}")
    if target.suffix == ".bag":
        _check_kwargs(src, kwargs, _BAG_OPTIONS, "a bag")
        return read_rosbag(target, **kwargs)
    if _looks_like_carmen(src):
        _check_kwargs(src, kwargs, ("range_max", "odometry_source", "laser_pose"), "a CARMEN log")
        return read_carmen(target, **kwargs)
    raise LogError(f"{src}: unrecognised log format; expected {_EXPECTED}")


_BAG_OPTIONS = ("scan_topic", "odom_topic", "odom_frame", "base_frame", "laser_pose", "max_scans")
_OPTION_NAMES = {"scan_topic": "--scan-topic", "odom_topic": "--odom-topic", "odometry_source": "--odometry",
                 "odom_frame": "--odom-frame", "base_frame": "--base-frame", "laser_pose": "--laser-pose"}


def _check_kwargs(src: str, kwargs: dict, allowed: tuple[str, ...], kind: str) -> None:
    """A LogError (not a TypeError) for an option the file's reader does not take."""
    extra = sorted(set(kwargs) - set(allowed))
    if extra:
        names = ", ".join(_OPTION_NAMES.get(k, k) for k in extra)
        raise LogError(f"{src}: {names} does not apply to {kind}")


def _looks_like_carmen(src: str) -> bool:
    """Whether the file's first non-comment lines are CARMEN messages leading to laser/odometry.

    Raises:
        LogError: for a text file that cannot be a log: UTF-16, empty, or only comments.
    """
    with open(src, "rb") as f:
        head = f.read(_SNIFF_BYTES)
    problem = text_problem(head)
    if problem:
        raise LogError(f"{src}: {problem}")
    head = head.removeprefix(b"\xef\xbb\xbf")  # a UTF-8 byte-order mark
    if b"\0" in head:
        return False  # binary
    data_lines = False
    for line in head.splitlines():
        fields = line.split()
        if not fields or fields[0].startswith(b"#"):
            continue
        data_lines = True
        name = fields[0]
        if name.decode("ascii", "replace") in _CARMEN_DATA:
            return True
        if not _CARMEN_NAME.match(name):
            return False
    if not data_lines and len(head) < _SNIFF_BYTES:
        raise LogError(f"{src}: {ONLY_COMMENTS}")
    return False
