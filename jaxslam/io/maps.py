"""Occupancy grid maps as ROS ``map_server`` files: a PGM (or PNG) image plus a YAML file.

The image's rows run top-down, the grid's rows bottom-up (row 0 at the ``origin``'s
y, see :mod:`jaxslam.grid`), so the image is the grid flipped vertically. With
``negate: 0`` a pixel value v means occupancy ``(255 - v) / 255``: 0 (black) is
occupied, 254 free and 205 unknown, the values ``map_saver`` writes.
:func:`crop_to_known` cuts a grid down to its observed cells plus a margin before writing.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from PIL import Image  # matplotlib's own dependency; writes the 8-bit image as it is
from ruamel.yaml import YAML  # a dependency of rosbags, so always installed with jaxslam

from jaxslam.grid import GridSpec
from jaxslam.laserlog import LogError

__all__ = ["DEFAULT_MARGIN_CELLS", "crop_to_known", "read_map", "write_map"]

OCCUPIED_PIXEL = 0
FREE_PIXEL = 254
UNKNOWN_PIXEL = 205

_REQUIRED_KEYS = ("image", "resolution", "origin")
_OPTIONAL_KEYS = {"negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196, "mode": "trinary"}
_MODES = ("trinary", "scale", "raw")

DEFAULT_MARGIN_CELLS = 20
"""Unknown cells kept around the known area by :func:`crop_to_known` (1 m at 5 cm cells)."""


def crop_to_known(logodds, spec: GridSpec, margin_cells: int = DEFAULT_MARGIN_CELLS) -> tuple[np.ndarray, GridSpec]:
    """The smallest sub-grid holding every known cell, plus ``margin_cells`` on each side.

    A cell is known where its log-odds is not 0 (a cell never observed is exactly 0). The
    margin is clipped to the grid. The returned spec's origin is the world position of the
    crop's lower-left corner, so every cell keeps its world position: cropped cell (i, j) is
    cell (i + r0, j + c0) of the input, with origin ``(ox + c0 * res, oy + r0 * res)``.
    A grid with no known cell gives its 1 x 1 corner cell (0, 0), origin unchanged, so that
    a map file can still be written.

    Args:
        logodds: (H, W) log-odds, H, W = ``spec.shape``, row 0 at the origin's y.
        spec: the grid's shape, resolution and origin.
        margin_cells: cells (>= 0) kept beyond the known bounding box on every side.

    Returns:
        The cropped (h, w) log-odds (a copy, the input's dtype) and its :class:`GridSpec`.
    """
    grid = np.asarray(logodds)
    if grid.shape != spec.shape:
        raise ValueError(f"logodds has shape {grid.shape}, the spec says {spec.shape}")
    if isinstance(margin_cells, bool) or int(margin_cells) != margin_cells or margin_cells < 0:
        raise ValueError(f"margin_cells must be a non-negative integer, got {margin_cells!r}")
    margin = int(margin_cells)
    known = grid != 0
    rows = np.flatnonzero(known.any(axis=1))
    cols = np.flatnonzero(known.any(axis=0))
    if rows.size == 0:
        return grid[:1, :1].copy(), GridSpec((1, 1), spec.resolution, spec.origin)
    height, width = grid.shape
    r0, r1 = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, height)
    c0, c1 = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, width)
    ox, oy = spec.origin
    cropped = GridSpec((r1 - r0, c1 - c0), spec.resolution, (ox + c0 * spec.resolution, oy + r0 * spec.resolution))
    return grid[r0:r1, c0:c1].copy(), cropped


def write_map(path_stem, logodds, spec: GridSpec, occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> dict:
    """Write a log-odds grid as ``<stem>.pgm`` + ``<stem>.yaml`` (map_server) + ``<stem>.png``.

    A cell is occupied (pixel 0) where ``p = sigmoid(logodds) > occupied_thresh``, free
    (254) where ``p < free_thresh`` and unknown (205) otherwise, as ``map_saver`` does.

    Args:
        path_stem: path without extension; the folder must exist.
        logodds: (H, W) occupancy log-odds (0 = unknown), H, W = ``spec.shape``; row i at
            y = origin_y + (i + 0.5) * resolution.
        spec: the grid's shape, resolution (m per cell) and origin (m, lower-left corner).
        occupied_thresh, free_thresh: probability thresholds, 0 <= free < 0.5 < occupied <= 1
            so that unknown cells (p = 0.5) stay unknown. Also written to the YAML.

    Returns:
        ``{"pgm": Path, "yaml": Path, "png": Path}``. The YAML's ``image`` is the PGM's file
        name (relative to the YAML); the PNG shows the same image (same orientation).
    """
    grid = np.asarray(logodds)
    if not np.issubdtype(grid.dtype, np.floating):
        grid = grid.astype(np.float64)
    if grid.shape != spec.shape:
        raise ValueError(f"logodds has shape {grid.shape}, the spec says {spec.shape}")
    if not np.all(np.isfinite(grid)):
        raise ValueError("logodds must be finite (no NaN or inf)")
    if not 0.0 <= free_thresh < 0.5 < occupied_thresh <= 1.0:
        raise ValueError(
            f"need 0 <= free_thresh < 0.5 < occupied_thresh <= 1, got {free_thresh}, {occupied_thresh}"
        )
    # p > threshold <=> log-odds > logit(threshold): compared in the map's own dtype, cell by
    # cell, so a large map (Killian's, 10^8 cells) costs no float64 copies.
    pixels = np.full(grid.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    if occupied_thresh < 1.0:
        pixels[grid > _logit(occupied_thresh)] = OCCUPIED_PIXEL
    if free_thresh > 0.0:
        pixels[grid < _logit(free_thresh)] = FREE_PIXEL
    image = np.ascontiguousarray(pixels[::-1])  # image row 0 is the top: the largest y

    stem = Path(os.fspath(path_stem))
    paths = {"pgm": stem.with_name(stem.name + ".pgm"), "yaml": stem.with_name(stem.name + ".yaml"),
             "png": stem.with_name(stem.name + ".png")}
    height, width = image.shape
    with open(paths["pgm"], "wb") as f:
        f.write(f"P5\n# CREATOR: jaxslam {spec.resolution:.6f} m/pix\n{width} {height}\n255\n".encode("ascii"))
        f.write(image.tobytes())
    ox, oy = (_nanometre(v) for v in spec.origin)
    paths["yaml"].write_text(
        f"image: {paths['pgm'].name}\n"
        f"mode: trinary\n"
        f"resolution: {spec.resolution!r}\n"
        f"origin: [{ox!r}, {oy!r}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {float(occupied_thresh)!r}\n"
        f"free_thresh: {float(free_thresh)!r}\n",
        encoding="utf-8",
    )
    Image.fromarray(image).save(paths["png"])  # uint8 (H, W): 8-bit grey
    return paths


def _nanometre(value) -> float:
    """``value`` (m) rounded to the nanometre, as a Python float: a grid's origin, computed as
    ``start + cells * resolution``, carries float noise (-12.350000000000001) that map.yaml need
    not show; a nanometre is far below any map's resolution."""
    return round(float(value), 9) + 0.0  # + 0.0: no "-0.0"


def _logit(p: float) -> np.float64:
    # np.float64, not float: NumPy then compares a float16 map in float64 (a Python float would be
    # rounded to float16 first), as the probabilities were compared before.
    return np.log(np.float64(p)) - np.log1p(-np.float64(p))


def read_map(yaml_path) -> tuple[np.ndarray, GridSpec]:
    """Read a map_server map (YAML + PGM/PNG image), e.g. one written by :func:`write_map`.

    The YAML needs ``image`` (relative to the YAML's folder, or absolute), ``resolution``
    (m per cell) and ``origin`` ([x, y, yaw], yaw 0: grids are axis-aligned); ``negate``
    (0), ``occupied_thresh`` (0.65), ``free_thresh`` (0.196) and ``mode`` (trinary,
    scale or raw) are optional. Other keys are an error (a misspelt key must not fall back
    to a default silently). Pixels follow map_server: occupancy ``occ = (255 - v) / 255``
    (``v / 255`` with negate 1; colour channels averaged). In trinary mode
    ``occ > occupied_thresh`` is 1.0, ``occ < free_thresh`` 0.0 and the rest unknown 0.5;
    in scale mode the values between the thresholds are scaled linearly into (0, 1) and
    transparent pixels are unknown; in raw mode v in 0..100 is v / 100, other values unknown.

    Returns:
        occupancy probability (H, W) float32 in [0, 1] (unknown 0.5, no NaN), rows bottom-up
        like the grid (row 0 at the origin's y), and its :class:`~jaxslam.grid.GridSpec`.

    Raises:
        LogError: naming the file, for a missing or unparsable YAML or image, a missing,
            unknown or invalid key.
    """
    src = os.fspath(yaml_path)
    meta = _read_yaml(src)
    image_path = Path(str(meta["image"]))
    if not image_path.is_absolute():
        image_path = Path(src).parent / image_path
    if not image_path.is_file():
        raise LogError(f"{src}: the map image {str(image_path)!r} named by 'image' does not exist")
    gray, alpha = _read_image(os.fspath(image_path))
    occupancy = gray / 255.0 if meta["negate"] else (255.0 - gray) / 255.0
    occupied_thresh, free_thresh = meta["occupied_thresh"], meta["free_thresh"]
    mode = meta["mode"]
    if mode == "trinary":
        probability = np.full(occupancy.shape, 0.5)
        probability[occupancy > occupied_thresh] = 1.0
        probability[occupancy < free_thresh] = 0.0
    elif mode == "scale":
        probability = np.clip((occupancy - free_thresh) / (occupied_thresh - free_thresh), 0.0, 1.0)
        probability[occupancy > occupied_thresh] = 1.0
        probability[occupancy < free_thresh] = 0.0
        probability[alpha < 1.0] = 0.5
    else:  # raw: the pixel value is the occupancy in percent
        probability = np.where(gray <= 100, gray / 100.0, 0.5)
    ox, oy, _ = meta["origin"]
    spec = GridSpec(probability.shape, meta["resolution"], (ox, oy))
    return np.ascontiguousarray(probability[::-1], dtype=np.float32), spec


def _read_yaml(src: str) -> dict:
    """The validated keys of a map YAML, defaults filled in."""
    try:
        text = Path(src).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise LogError(f"{src}: no such map YAML file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise LogError(f"{src}: cannot read the map YAML ({err})") from None
    try:
        meta = YAML(typ="safe", pure=True).load(text)
    except Exception as err:  # ruamel's parser and scanner errors have no common public base
        raise LogError(f"{src}: not valid YAML ({err})") from None
    if not isinstance(meta, dict):
        raise LogError(f"{src}: expected a mapping of map_server keys, got {type(meta).__name__}")
    missing = [k for k in _REQUIRED_KEYS if k not in meta]
    if missing:
        raise LogError(f"{src}: missing key(s) {missing}; a map YAML needs {list(_REQUIRED_KEYS)}")
    unknown = sorted(str(k) for k in meta if k not in _REQUIRED_KEYS and k not in _OPTIONAL_KEYS)
    if unknown:
        raise LogError(
            f"{src}: unknown key(s) {unknown}; expected {list(_REQUIRED_KEYS) + list(_OPTIONAL_KEYS)}"
        )
    result = dict(_OPTIONAL_KEYS)
    result.update(meta)
    if not isinstance(result["image"], str) or not result["image"]:
        raise LogError(f"{src}: 'image' must be a file name, got {result['image']!r}")
    result["resolution"] = _positive_number(src, "resolution", result["resolution"])
    origin = result["origin"]
    if not isinstance(origin, list) or len(origin) not in (2, 3):
        raise LogError(f"{src}: 'origin' must be [x, y, yaw], got {origin!r}")
    origin = [_number(src, "origin", v) for v in origin] + [0.0] * (3 - len(origin))
    if origin[2] != 0.0:
        raise LogError(
            f"{src}: 'origin' yaw {origin[2]} is not 0; rotated maps are not supported (grids are axis-aligned)"
        )
    result["origin"] = origin
    if result["negate"] not in (0, 1, True, False):
        raise LogError(f"{src}: 'negate' must be 0 or 1, got {result['negate']!r}")
    for key in ("occupied_thresh", "free_thresh"):
        result[key] = _number(src, key, result[key])
        if not 0.0 <= result[key] <= 1.0:
            raise LogError(f"{src}: {key!r} must lie in [0, 1], got {result[key]}")
    if not result["free_thresh"] < result["occupied_thresh"]:
        raise LogError(
            f"{src}: free_thresh {result['free_thresh']} must be below occupied_thresh {result['occupied_thresh']}"
        )
    if result["mode"] not in _MODES:
        raise LogError(f"{src}: 'mode' must be one of {list(_MODES)}, got {result['mode']!r}")
    return result


def _number(src: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise LogError(f"{src}: {key!r} must be a finite number, got {value!r}")
    return float(value)


def _positive_number(src: str, key: str, value) -> float:
    number = _number(src, key, value)
    if not number > 0:
        raise LogError(f"{src}: {key!r} must be positive, got {value!r}")
    return number


def _read_image(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Grey level (H, W) float64 in 0..255 (colour channels averaged) and alpha (H, W) in [0, 1]."""
    with open(path, "rb") as f:
        magic = f.read(2)
    if magic in (b"P5", b"P2"):
        gray = _read_pgm(path)
        return gray, np.ones_like(gray)
    import matplotlib.image

    try:
        pixels = np.asarray(matplotlib.image.imread(path))
    except Exception as err:  # Pillow raises format-specific errors
        raise LogError(f"{path}: cannot read the map image ({type(err).__name__}: {err})") from None
    if np.issubdtype(pixels.dtype, np.integer):
        scaled = pixels.astype(np.float64) * (255.0 / np.iinfo(pixels.dtype).max)
    else:  # matplotlib reads PNGs as floats in [0, 1]
        scaled = pixels.astype(np.float64) * 255.0
    if scaled.ndim == 2:
        return scaled, np.ones_like(scaled)
    if scaled.ndim != 3 or scaled.shape[2] not in (2, 3, 4):
        raise LogError(f"{path}: unexpected image shape {pixels.shape}")
    channels = scaled.shape[2]
    has_alpha = channels in (2, 4)
    color = scaled[..., : channels - 1] if has_alpha else scaled
    alpha = scaled[..., -1] / 255.0 if has_alpha else np.ones(scaled.shape[:2])
    return color.mean(axis=-1), alpha


def _read_pgm(path: str) -> np.ndarray:
    """A binary (P5) or ASCII (P2) PGM as (H, W) float64 grey levels scaled to 0..255."""
    data = Path(path).read_bytes()
    tokens: list[bytes] = []
    pos = 0
    # Header: magic, width, height, maxval, separated by whitespace, with '#' comments.
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if pos < len(data) and data[pos : pos + 1] == b"#":
            while pos < len(data) and data[pos : pos + 1] not in (b"\n", b"\r"):
                pos += 1
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace() and data[pos : pos + 1] != b"#":
            pos += 1
        if start == pos:
            raise LogError(f"{path}: truncated PGM header")
        tokens.append(data[start:pos])
    try:
        width, height, maxval = (int(t) for t in tokens[1:])
    except ValueError:
        raise LogError(f"{path}: bad PGM header {b' '.join(tokens)!r}") from None
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise LogError(f"{path}: bad PGM size {width}x{height} or maxval {maxval}")
    count = width * height
    if tokens[0] == b"P5":
        pos += 1  # exactly one whitespace byte separates the header from the pixels
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
        if len(data) - pos < count * dtype.itemsize:
            raise LogError(
                f"{path}: truncated PGM: {len(data) - pos} bytes of pixels, expected {count * dtype.itemsize}"
            )
        values = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
    else:
        try:
            values = np.asarray(data[pos:].split(), dtype=np.int64)
        except ValueError:
            raise LogError(f"{path}: non-numeric pixel in ASCII PGM") from None
        if values.size != count:
            raise LogError(f"{path}: ASCII PGM has {values.size} pixels, expected {count}")
    if np.any(values > maxval):
        raise LogError(f"{path}: PGM pixel above maxval {maxval}")
    return values.reshape(height, width).astype(np.float64) * (255.0 / maxval)
