"""A world to drive in: a map in the nav2 map_server format and a simulated planar lidar.

    world = load_world("config/worlds/room.yaml")          # the YAML names its PGM image
    ranges = world.scan(Pose2D(x, y, yaw), angles, range_max=8.0, circles=[(cx, cy, r)])

The map file is map_server's (docs: nav2 "Map Server"): `image` (relative to the YAML), `resolution`
(m per pixel), `origin` [x, y, yaw] of the lower-left pixel in the map frame, `negate`,
`occupied_thresh`, `free_thresh` (mode trinary). A pixel's occupancy probability is (255 - p) / 255
((p / 255 with negate); above occupied_thresh it is occupied (100), below free_thresh free (0), else
unknown (-1); the image's first row is the map's top, so the grid (an OccupancyGrid's cells, row 0 at
the bottom) is the image flipped. The map frame is the odometry frame here (a simulated robot's odometry
does not drift; REP 105).

The lidar casts each beam through the grid at half a cell per step (the first occupied cell it enters;
unknown cells do not return) and against moving circles (the walkers of a scene, core/perception/
raycast.py); a beam with nothing within range_max returns +inf (REP 117).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from ..config.params_file import default_config_path
from ..errors import ConfigError
from ..perception.grid import Grid
from ..perception.raycast import cast
from ..perception.scan import Pose2D

#: occupancy values of the grid (percent, OccupancyGrid's convention)
OCCUPIED, FREE, UNKNOWN = 100, 0, -1
#: the map file's keys and their defaults (map_server's)
MAP_DEFAULTS = {"negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196, "mode": "trinary"}
#: ray-marching steps per cell
STEPS_PER_CELL = 2


@dataclass(frozen=True)
class World:
    """A map as an occupancy grid (`grid`, core/perception/grid.py) and the file it came from."""

    grid: Grid
    source: str = ""

    @property
    def size(self) -> tuple[float, float]:
        """Width and height of the map, m."""
        height, width = self.grid.cells.shape
        return width * self.grid.resolution, height * self.grid.resolution

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """Whether each point [..., 2] (m, map frame) lies in an occupied cell (outside the map: no)."""
        g = self.grid
        local = Pose2D(0.0, 0.0, -g.origin.yaw).apply(np.reshape(points, (-1, 2)) - g.origin.position)
        cols, rows = np.floor(local / g.resolution).astype(int).T
        height, width = g.cells.shape
        inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
        hit = np.zeros(len(local), bool)
        hit[inside] = g.cells[rows[inside], cols[inside]] >= OCCUPIED
        return hit.reshape(np.shape(points)[:-1])

    def scan(self, sensor: Pose2D, angles: np.ndarray, range_max: float, range_min: float = 0.0,
             circles: Sequence[tuple[float, float, float]] = (),
             segments: Sequence[tuple[float, float, float, float]] = ()) -> np.ndarray:
        """Ranges [B] (m; +inf: no return within range_max) of beams at `angles` [B] (rad, sensor frame) from
        `sensor` (pose in the map frame) to the first occupied cell, circle (cx, cy, r) or segment (x0, y0, x1, y1)."""
        angles = np.asarray(angles, float)
        step = self.grid.resolution / STEPS_PER_CELL
        t = np.arange(max(range_min, step), range_max + step, step)  # [T]
        heading = sensor.yaw + angles
        d = np.column_stack([np.cos(heading), np.sin(heading)])  # [B, 2]
        points = sensor.position[None, None, :] + t[None, :, None] * d[:, None, :]  # [B, T, 2]
        hit = self.occupied(points)  # [B, T]
        first = np.argmax(hit, axis=1)
        walls = np.where(hit.any(axis=1), t[first], np.inf)
        moving = len(circles) or len(segments)
        ranges = np.minimum(walls, cast(sensor, angles, segments, circles, range_max)) if moving else walls
        ranges[(ranges > range_max) | (ranges < range_min)] = np.inf
        return ranges


def _image_cells(image: np.ndarray, negate: bool, occupied_thresh: float, free_thresh: float) -> np.ndarray:
    """Occupancy [rows, cols] int8 of a greyscale image (uint8, first row the top), rows flipped to the grid's."""
    p = image.astype(float) / 255.0
    occupancy = p if negate else 1.0 - p
    cells = np.full(image.shape, UNKNOWN, np.int8)
    cells[occupancy > occupied_thresh] = OCCUPIED
    cells[occupancy < free_thresh] = FREE
    return cells[::-1].copy()


def find_world(name: str | Path) -> Path:
    """A map file: the path as given (absolute, or relative to the working directory), else relative to the
    shipped config folder (`worlds/room.yaml`: the package's config/worlds/room.yaml, also when installed)."""
    path = Path(name)
    if path.exists() or path.is_absolute():
        return path
    shipped = default_config_path().parent / path
    return shipped if shipped.exists() else path


def load_world(path: str | Path) -> World:
    """The map of a map_server YAML file (`find_world`; module doc); ConfigError naming the file and what is
    wrong."""
    from PIL import Image, UnidentifiedImageError  # Pillow (matplotlib's dependency) reads PGM, PNG, ...

    path = find_world(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"map {path}: cannot read it: {exc}") from exc
    if not isinstance(data, dict) or "image" not in data or "resolution" not in data or "origin" not in data:
        raise ConfigError(f"map {path}: a map_server YAML needs image, resolution and origin")
    values = {**MAP_DEFAULTS, **data}
    if values["mode"] != "trinary":
        raise ConfigError(f"map {path}: mode {values['mode']!r} is not supported (trinary only)")
    try:
        resolution = float(values["resolution"])
        origin = [float(v) for v in values["origin"]]
        negate = bool(int(values["negate"]))
        occupied_thresh, free_thresh = float(values["occupied_thresh"]), float(values["free_thresh"])
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"map {path}: {exc}") from exc
    if not (math.isfinite(resolution) and resolution > 0) or len(origin) != 3 or \
            not all(math.isfinite(v) for v in origin) or not 0 <= free_thresh < occupied_thresh <= 1:
        raise ConfigError(f"map {path}: resolution must be > 0, origin [x, y, yaw] finite and "
                          f"0 <= free_thresh < occupied_thresh <= 1")
    image_path = path.parent / str(values["image"])
    try:
        with Image.open(image_path) as image:
            pixels = np.asarray(image.convert("L"))
    except (OSError, UnidentifiedImageError) as exc:
        raise ConfigError(f"map {path}: cannot read its image {image_path}: {exc}") from exc
    cells = _image_cells(pixels, negate, occupied_thresh, free_thresh)
    return World(Grid(cells, resolution, Pose2D(*origin)), str(path))


def save_world(path: str | Path, cells: np.ndarray, resolution: float, origin: Sequence[float] = (0.0, 0.0, 0.0)
               ) -> Path:
    """Write cells [rows, cols] (grid rows, row 0 at the bottom; OCCUPIED/FREE/UNKNOWN) as a map_server YAML
    and its PGM beside it (the worlds in config/worlds/ are made so); returns the YAML's path."""
    from PIL import Image

    path = Path(path)
    pixels = np.full(cells.shape, 205, np.uint8)  # unknown: map_saver's grey
    pixels[cells == OCCUPIED], pixels[cells == FREE] = 0, 254
    Image.fromarray(pixels[::-1]).save(path.with_suffix(".pgm"))
    path.write_text(yaml.safe_dump({"image": path.with_suffix(".pgm").name, "resolution": float(resolution),
                                    "origin": [float(v) for v in origin], "negate": 0, "occupied_thresh": 0.65,
                                    "free_thresh": 0.196, "mode": "trinary"}, sort_keys=False))
    return path
