"""The CarRacing renderer (gymnasium's scene, the reference implementation's camera), numpy-vectorized
over env copies.

Gymnasium draws about 800 polygons per frame with pygame on a 1000x800 surface and scales it down to
96x96; here each level's track is rasterized once, at reset, into a top-down map of classes (outside,
grass, grass patch, road, white and red kerb) at PIXELS_PER_UNIT cells per world unit. An observation is
then one nearest-neighbour gather of the 96x96 window around each car, turned as the reference
implementation's (dcd) camera turns (with the car's direction of travel, see camera_angle; the car three
quarters down the image, gymnasium's zoom and the same non-square pixel footprint its 1000x800 -> 96x96
scaling gives), plus the car (hull, wheels with their rotating stripe) and the indicator bar (true
speed, four ABS sensors, steering, gyroscope), drawn as gymnasium draws them, and one palette lookup.
Pixels are lit when their centre is inside a shape.

Left out of gymnasium's picture: the zoom animation of the first second (the reference disables it),
skid marks (not drawn in state pixels), the score digits in the bar, and the 1-2% brightness
variation between untouched road tiles (all road has the colour of a touched tile).
"""

from __future__ import annotations

import math

import numpy as np

from envs.carracing.tracks import BORDER, TRACK_WIDTH, Track

STATE_SIZE = 96
WINDOW_W, WINDOW_H = 1000, 800  # gymnasium's surface, scaled to 96x96
ZOOM = 2.7 * 6.0  # gymnasium's ZOOM * SCALE: surface pixels per world unit
UNITS_PER_PIXEL_X = WINDOW_W / STATE_SIZE / ZOOM  # 0.643 world units per state pixel across
UNITS_PER_PIXEL_Y = WINDOW_H / STATE_SIZE / ZOOM  # 0.514 along
CAR_ROW = STATE_SIZE * 3 / 4  # the car's position in the image: column 48, row 72 (continuous)
CAR_COLUMN = STATE_SIZE / 2
PIXELS_PER_UNIT = 2.0  # class-map resolution
# OUTSIDE cells around the playfield in a class map: the farthest pixel of a view is 48.2 world units
# from the car, whose rendered centre is clamped to 5 units beyond the playfield, so no lookup leaves
# the map (and none needs clipping).
MAP_MARGIN = math.ceil(55 * PIXELS_PER_UNIT)

# Car geometry (gymnasium's car_dynamics, times SIZE = 0.02).
CAR_SIZE = 0.02
HULL_POLYGONS = [
    [(-60, +130), (+60, +130), (+60, +110), (-60, +110)],
    [(-15, +120), (+15, +120), (+20, +20), (-20, 20)],
    [(+25, +20), (+50, -10), (+50, -40), (+20, -90), (-20, -90), (-50, -40), (-50, -10), (-25, +20)],
    [(-50, -120), (+50, -120), (+50, -90), (-50, -90)],
]
WHEEL_HALF_WIDTH = 14 * CAR_SIZE
WHEEL_HALF_LENGTH = 27 * CAR_SIZE
# A wheel's pixels have their centres within hypot(half width, half length) = 0.608 world units of the
# wheel's centre. They lie in its block: from the first row (column) whose centre is at most WHEEL_REACH
# before the wheel's centre, 3 rows (2 columns), as the next one's centre would be 3 x 0.514 = 1.54
# (2 x 0.643 = 1.29) units on, beyond the wheel's far reach, 0.625 + 0.608 = 1.23 units on.
WHEEL_REACH = 0.625
WHEEL_BLOCK_ROWS, WHEEL_BLOCK_COLUMNS = 3, 2

# Classes and their colours (gymnasium's default colours).
OUTSIDE, BACKGROUND, GRASS, ROAD, KERB_WHITE, KERB_RED, HULL, WHEEL, WHEEL_STRIPE, BAR = range(10)
SPEED, ABS_FRONT, ABS_REAR, STEERING, GYROSCOPE = range(10, 15)
PALETTE = np.array(
    [
        [0, 0, 0],  # OUTSIDE
        [102, 204, 102],  # BACKGROUND (gymnasium's bg_color)
        [102, 230, 102],  # GRASS patch (grass_color)
        [102, 102, 102],  # ROAD (road_color)
        [255, 255, 255],  # KERB_WHITE
        [255, 0, 0],  # KERB_RED
        [204, 0, 0],  # HULL (0.8, 0, 0)
        [0, 0, 0],  # WHEEL
        [77, 77, 77],  # WHEEL_STRIPE
        [0, 0, 0],  # BAR
        [255, 255, 255],  # SPEED
        [0, 0, 255],  # ABS_FRONT
        [51, 0, 255],  # ABS_REAR
        [0, 255, 0],  # STEERING
        [255, 0, 0],  # GYROSCOPE
    ],
    dtype=np.uint8,
)
PALETTE_CHANNELS = np.ascontiguousarray(PALETTE.T)  # [3, classes]: one lookup per channel gives CHW

GREEN_LEVELS = PALETTE[:, 1].astype(np.float64)  # each class's green channel
GREEN_CHANNEL = PALETTE_CHANNELS[1]  # the same, uint8 (sums of uint8 levels are exact integers)

# The car's neighbourhood in the image, where wheels are drawn however they are turned (rows 60-83,
# columns 40-55; they reach 2.6 world units from the car's centre: 5 rows or 4 columns).
CAR_ROWS = slice(60, 84)
CAR_COLUMNS = slice(40, 56)
BAR_TOP = 84  # the indicator bar's first row: it covers the bottom 5/40 of the image
# The reference's camera follows the direction of travel above this speed (world units per second).
CAMERA_SPEED = 0.5


# ---------------------------------------------------------------------------------------------------
# Class maps: a track rasterized once per level.
# ---------------------------------------------------------------------------------------------------
def fill_triangles(raster: np.ndarray, triangles: np.ndarray, value: int) -> None:
    """Set to `value` every cell of raster [R, C] whose centre is inside one of triangles [Q, 3, 2]
    ((column, row) in continuous raster coordinates: cell (r, c) spans [c, c+1) x [r, r+1)).

    Scanlines for all triangles at once: each (triangle, row) pair gives a span of columns between its
    two edge crossings; the spans' cells are enumerated with one repeat + arange and written at once."""
    if len(triangles) == 0:
        return
    rows_total, cols_total = raster.shape
    ys = triangles[..., 1]
    first = np.maximum(np.ceil(ys.min(axis=1) - 0.5).astype(np.int64), 0)
    last = np.minimum(np.floor(ys.max(axis=1) - 0.5).astype(np.int64), rows_total - 1)
    span = int((last - first).max()) + 1
    if span <= 0:
        return
    rows = first[:, None] + np.arange(span)[None, :]
    centre = rows + 0.5
    left = np.full(rows.shape, np.inf)
    right = np.full(rows.shape, -np.inf)
    for e in range(3):
        p, q = triangles[:, e, None, :], triangles[:, (e + 1) % 3, None, :]
        crosses = ((p[..., 1] <= centre) & (centre < q[..., 1])) | ((q[..., 1] <= centre) & (centre < p[..., 1]))
        dy = np.where(crosses, q[..., 1] - p[..., 1], 1.0)
        x = p[..., 0] + (centre - p[..., 1]) * (q[..., 0] - p[..., 0]) / dy
        left = np.where(crosses, np.minimum(left, x), left)
        right = np.where(crosses, np.maximum(right, x), right)
    start = np.maximum(np.ceil(left - 0.5), 0)
    stop = np.minimum(np.floor(right - 0.5), cols_total - 1)
    ok = (rows <= last[:, None]) & (start <= stop)
    begin = rows[ok] * cols_total + start[ok].astype(np.int64)
    length = (stop[ok] - start[ok]).astype(np.int64) + 1
    offsets = np.repeat(begin - (np.cumsum(length) - length), length)
    raster.reshape(-1)[offsets + np.arange(len(offsets))] = value


_BASE_MAPS: dict = {}


def base_map(playfield: float, pixels_per_unit: float, margin: int) -> np.ndarray:
    """The class map of an empty playfield: grass with the lighter patches of gymnasium (a checkerboard
    quarter of squares of playfield/20, as the reference draws them), inside a ring of `margin`
    OUTSIDE cells (black, as gymnasium's surface beyond the playfield)."""
    key = (playfield, pixels_per_unit, margin)
    if key not in _BASE_MAPS:
        cells = math.ceil(2 * playfield * pixels_per_unit)
        centre = (np.arange(cells) + 0.5) / pixels_per_unit - playfield
        patch = np.floor(centre / (playfield / 20)).astype(np.int64) % 2 == 0
        inner = np.where(patch[:, None] & patch[None, :], GRASS, BACKGROUND).astype(np.uint8)
        _BASE_MAPS[key] = np.pad(inner, margin, constant_values=OUTSIDE)
    return _BASE_MAPS[key]


def track_quads(track: Track, inner: float, outer: float, side: np.ndarray | None = None) -> np.ndarray:
    """Quads [T, 4, 2] of each tile between offsets inner..outer from the centreline along the cross
    direction (road: -W..W; kerb: side*W..side*(W+BORDER)); tile k spans points k - 1 and k."""
    normal = np.stack([np.cos(track.beta), np.sin(track.beta)], axis=1)
    scale_in = inner if side is None else inner * side[:, None]
    scale_out = outer if side is None else outer * side[:, None]
    here_in, here_out = track.xy + scale_in * normal, track.xy + scale_out * normal
    prev_xy, prev_normal = np.roll(track.xy, 1, axis=0), np.roll(normal, 1, axis=0)
    prev_in, prev_out = prev_xy + scale_in * prev_normal, prev_xy + scale_out * prev_normal
    return np.stack([here_in, here_out, prev_out, prev_in], axis=1)


def quads_to_triangles(quads: np.ndarray) -> np.ndarray:
    """Each quad [Q, 4, 2] as two triangles (0, 1, 2) and (0, 2, 3): [2Q, 3, 2]."""
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def class_map(track: Track, pixels_per_unit: float = PIXELS_PER_UNIT, margin: int = MAP_MARGIN) -> np.ndarray:
    """The track's class map [R, R] (row 0 at the bottom: y = -playfield - margin cells): grass, then
    kerbs, then road on top. World point (x, y) is cell (floor((y + playfield) * ppu) + margin,
    floor((x + playfield) * ppu) + margin)."""
    raster = base_map(track.playfield, pixels_per_unit, margin).copy()

    def to_raster(xy):
        """World points to continuous map coordinates."""
        return (xy + track.playfield) * pixels_per_unit + margin

    kerbs = track_quads(track, TRACK_WIDTH, TRACK_WIDTH + BORDER, side=track.kerb_side.astype(np.float64))
    for stripe, value in ((0, KERB_WHITE), (1, KERB_RED)):
        chosen = track.kerb & (track.stripe == stripe)
        fill_triangles(raster, quads_to_triangles(to_raster(kerbs[chosen])), value)
    fill_triangles(raster, quads_to_triangles(to_raster(track_quads(track, -TRACK_WIDTH, TRACK_WIDTH))), ROAD)
    return raster


# ---------------------------------------------------------------------------------------------------
# Top-down images of whole levels, and driven trajectories over them.
# ---------------------------------------------------------------------------------------------------
LEVEL_IMAGE_SIZE = 128
TRAJECTORY_COLOUR = np.array([40, 60, 230], dtype=np.uint8)
START_COLOUR = np.array([230, 40, 40], dtype=np.uint8)


def level_image(track: Track, size: int = LEVEL_IMAGE_SIZE) -> np.ndarray:
    """A top-down RGB image [size, size, 3] of the whole playfield (north up), the start marked red."""
    ppu = size / (2 * track.playfield)
    image = PALETTE[class_map(track, ppu, margin=0)[::-1]]
    return draw_trajectory(image, track.xy[:1], track.playfield, colour=START_COLOUR, radius=1)


def draw_trajectory(image: np.ndarray, xy: np.ndarray, playfield: float, colour=TRAJECTORY_COLOUR, radius: int = 0) -> np.ndarray:
    """A copy of a level image with world points xy [T, 2] (e.g. a driven path) marked in `colour`."""
    out = image.copy()
    size = out.shape[0]
    pixel = np.floor((np.asarray(xy, dtype=np.float64) + playfield) * size / (2 * playfield)).astype(np.int64)
    for dr in range(-radius, radius + 1):
        for dc in range(-radius, radius + 1):
            rows = np.clip(size - 1 - pixel[:, 1] + dr, 0, size - 1)
            cols = np.clip(pixel[:, 0] + dc, 0, size - 1)
            out[rows, cols] = colour
    return out


# ---------------------------------------------------------------------------------------------------
# The student's view.
# ---------------------------------------------------------------------------------------------------
def camera_angle(hull_angle: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """The angle the view is turned to [N], as a hull angle (the view shows a hull at this angle
    pointing up), by the reference implementation's (dcd) rule in CarRacingBezier.render: its camera
    rotation is atan2(vx, vy) (the direction of the hull's velocity [N, 2] points up) when the hull's
    speed |v| exceeds 0.5, else -hull angle (the hull points up). Rotation r is hull angle -r, so the
    angle is atan2(-vx, vy) or the hull's. (Gymnasium's camera always follows the hull.)"""
    vx, vy = velocity[:, 0], velocity[:, 1]
    return np.where(np.hypot(vx, vy) > CAMERA_SPEED, np.arctan2(-vx, vy), hull_angle)


def _pixel_offsets() -> tuple[np.ndarray, np.ndarray]:
    """World offsets (across, along) [96, 96] of each state pixel's centre from the car, in the
    camera's frame (along = up in the image; across = to its right)."""
    centres = np.arange(STATE_SIZE) + 0.5
    across = (centres - CAR_COLUMN) * UNITS_PER_PIXEL_X
    along = (CAR_ROW - centres) * UNITS_PER_PIXEL_Y
    return np.broadcast_to(across[None, :], (STATE_SIZE, STATE_SIZE)), np.broadcast_to(along[:, None], (STATE_SIZE, STATE_SIZE))


def _edges(polygon: np.ndarray) -> tuple[np.ndarray, ...]:
    """A polygon's [V, 2] edges: start x, y and direction (end - start) x, y, each [V, 1, 1] (one
    edge per entry, ready to meet 2-D arrays of points)."""
    start, direction = polygon, np.roll(polygon, -1, axis=0) - polygon
    return tuple(column.reshape(-1, 1, 1) for column in (start[:, 0], start[:, 1], direction[:, 0], direction[:, 1]))


def _inside_convex(px: np.ndarray, py: np.ndarray, edges: tuple[np.ndarray, ...]) -> np.ndarray:
    """Points [R, C] inside a convex polygon (either winding), given by its _edges: on the same side
    of every edge. All edges are tested at once."""
    ax, ay, dx, dy = edges
    signs = dx * (py - ay) - dy * (px - ax)
    return np.all(signs >= 0, axis=0) | np.all(signs <= 0, axis=0)


def _sums(levels: np.ndarray) -> np.ndarray:
    """The sum of each uint8 image [N, ...] of levels, int64 [N] (summed in uint32: exact, as an image
    of 96 x 96 holds at most 2.4 million)."""
    return levels.reshape(len(levels), -1).sum(axis=1, dtype=np.uint32).astype(np.int64)


class ViewRenderer:
    """Renders the 96x96 views of env copies at once from their class maps and car states: `classes`
    gives class images, `colours` turns them into RGB views (`render` does both) and `green_means`
    gives the mean green of each view (the reference's grass test); `green_means_of_views` gives the
    same means straight from the car states, without whole class images."""

    def __init__(self):
        self.across, self.along = _pixel_offsets()
        self.across_cells = (self.across[0] * PIXELS_PER_UNIT).astype(np.float32)  # of each column, in map cells
        self.along_cells = (self.along[:, 0] * PIXELS_PER_UNIT).astype(np.float32)  # of each row
        self.hull_polygons = [np.array(polygon, dtype=np.float64) * CAR_SIZE for polygon in HULL_POLYGONS]
        self.hull_edges = [_edges(polygon) for polygon in self.hull_polygons]
        self.car_across = self.across[CAR_ROWS, CAR_COLUMNS]
        self.car_along = self.along[CAR_ROWS, CAR_COLUMNS]
        reach = max(np.hypot(polygon[:, 0], polygon[:, 1]).max() for polygon in self.hull_polygons)
        # The pixels of the car's window the hull may cover, however turned (it reaches 2.9 world units
        # from the car's centre: 6 rows or 5 columns, inside the window).
        self.hull_pixels = np.nonzero(np.hypot(self.car_across, self.car_along) <= reach)
        self.hull_across, self.hull_along = self.car_across[self.hull_pixels], self.car_along[self.hull_pixels]
        self.bar_centres = np.arange(STATE_SIZE) + 0.5
        # Gymnasium's vertical indicators (speed, then the ABS sensors of wheels 0-3) at places 5, 7,
        # 8, 9, 10 of 40 across: the image columns of each, their bar's index and its class. No two
        # bars share a column, so they can be drawn at once.
        unit = STATE_SIZE / 40.0
        columns = [np.nonzero((self.bar_centres >= place * unit) & (self.bar_centres <= (place + 1) * unit))[0] for place in (5, 7, 8, 9, 10)]
        self.vertical_columns = np.concatenate(columns)
        self.vertical_bar = np.repeat(np.arange(len(columns)), [len(c) for c in columns])
        self.vertical_classes = np.array([SPEED, ABS_FRONT, ABS_FRONT, ABS_REAR, ABS_REAR], dtype=np.uint8)[self.vertical_bar]
        # The rows of the horizontal indicators (steering, gyroscope): centres within [H - 4h, H - 2h].
        band = np.nonzero((self.bar_centres >= STATE_SIZE - 4 * unit) & (self.bar_centres <= STATE_SIZE - 2 * unit))[0]
        self.horizontal_rows = slice(band[0], band[-1] + 1)

    def set_maps(self, maps: list[np.ndarray], playfields: np.ndarray) -> None:
        """The class map of each copy (copies may share one map object: it is stored once)."""
        unique = {}
        for m in maps:
            unique.setdefault(id(m), m)
        offsets, start = {}, 0
        for key, m in unique.items():
            offsets[key] = start
            start += m.size
        self.flat = np.empty(start, dtype=np.uint8)
        for key, m in unique.items():
            self.flat[offsets[key] : offsets[key] + m.size] = m.reshape(-1)
        self.green_flat = GREEN_CHANNEL[self.flat]  # the maps' green levels, for the grass test
        self.offset = np.array([offsets[id(m)] for m in maps], dtype=np.int32)
        self.width = np.array([m.shape[0] for m in maps], dtype=np.int32)
        self.playfield = np.asarray(playfields, dtype=np.float64)

    def _map_index(self, copies: np.ndarray, x: np.ndarray, y: np.ndarray, angle: np.ndarray, rows: int = STATE_SIZE) -> np.ndarray:
        """Flat indices into the stored maps [len(copies), rows, 96] of the view's pixels (its first
        `rows` rows) for copies whose cameras are at x, y turned to `angle` (camera_angle)
        [len(copies)], each in its copy's map. The centre is clamped to 5 units beyond the playfield
        (rendered cars are inside it), so every coordinate is positive and truncation is the floor."""
        playfield = self.playfield[copies]
        cx = np.clip(x, -playfield - 5, playfield + 5)
        cy = np.clip(y, -playfield - 5, playfield + 5)
        col0 = ((cx + playfield) * PIXELS_PER_UNIT + MAP_MARGIN).astype(np.float32)[:, None]
        row0 = ((cy + playfield) * PIXELS_PER_UNIT + MAP_MARGIN).astype(np.float32)[:, None]
        cos = np.cos(angle).astype(np.float32)[:, None]
        sin = np.sin(angle).astype(np.float32)[:, None]
        across, along = self.across_cells, self.along_cells[:rows]
        # A pixel's map column is col0 + cos * across - sin * along, its row row0 + sin * across +
        # cos * along: the first two terms depend on its column alone, the last on its row, so they
        # are formed once per column and per row (the float32 operations per pixel stay the same).
        col = ((col0 + cos * across)[:, None, :] - (sin * along)[:, :, None]).astype(np.int32)
        row = ((row0 + sin * across)[:, None, :] + (cos * along)[:, :, None]).astype(np.int32)
        row *= self.width[copies, None, None]
        row += col
        row += self.offset[copies, None, None]
        return row

    def classes(self, car: dict, copies: np.ndarray) -> np.ndarray:
        """uint8 class images [len(copies), 96, 96] of the views of the given copies (indices) from
        their car states (arrays with one row per copy, in the order of `copies`): hull x, y, angle,
        velocity [., 2]; wheel_xy [., 4, 2] and wheel_angle [., 4] relative to the hull (in its frame),
        wheel_phase [., 4], speed, wheel_omega [., 4], steering (front-left joint angle), angular
        velocity."""
        camera = camera_angle(car["angle"], car["velocity"])
        classes = self.flat.take(self._map_index(copies, car["x"], car["y"], camera))
        tilt = car["angle"] - camera  # the hull's angle in the view
        window = classes[:, CAR_ROWS, CAR_COLUMNS]
        self._draw_wheels(window, car, tilt)
        self._draw_hull(window, tilt)
        self._draw_indicators(classes, car)
        return classes

    def green_means_of_views(self, car: dict, copies: np.ndarray) -> np.ndarray:
        """The mean green of each copy's view [len(copies)] (arguments as for `classes`): equal, bit
        for bit, to green_means(classes(car, copies)), without drawing whole class images.

        The view's green sum is put together from parts: the maps' green levels under rows 0-83,
        gathered from the green maps; in the car's window, the green of its classes drawn with wheels
        and hull in place of their map's; and the green of the indicator bar (rows 84-95), drawn on its
        own. Green levels are integers, summed exactly, so the mean is the one green_means forms. A copy
        whose vertical indicator reaches above the bar (a speed over 210 or a wheel spinning at over
        420 rad/s) is rendered whole instead."""
        count = len(copies)
        camera = camera_angle(car["angle"], car["velocity"])
        tilt = car["angle"] - camera
        index = self._map_index(copies, car["x"], car["y"], camera, BAR_TOP)
        green = _sums(self.green_flat.take(index))
        window = self.flat.take(index[:, CAR_ROWS, CAR_COLUMNS])
        green -= _sums(GREEN_CHANNEL.take(window))
        self._draw_wheels(window, car, tilt)
        self._draw_hull(window, tilt)
        green += _sums(GREEN_CHANNEL.take(window))
        bar = np.empty((count, STATE_SIZE - BAR_TOP, STATE_SIZE), dtype=np.uint8)
        reaching_above = self._draw_indicators(bar, car)
        green += _sums(GREEN_CHANNEL.take(bar))
        means = green / (STATE_SIZE * STATE_SIZE)
        if reaching_above.any():
            whole = {key: value[reaching_above] for key, value in car.items()}
            means[reaching_above] = self.green_means(self.classes(whole, copies[reaching_above]))
        return means

    @staticmethod
    def colours(classes: np.ndarray) -> np.ndarray:
        """uint8 RGB views [N, 3, 96, 96] of class images [N, 96, 96]."""
        lookup = classes.astype(np.intp)
        view = np.empty((len(classes), 3, STATE_SIZE, STATE_SIZE), dtype=np.uint8)
        for channel in range(3):
            view[:, channel] = PALETTE_CHANNELS[channel][lookup]
        return view

    @staticmethod
    def green_means(classes: np.ndarray) -> np.ndarray:
        """The mean of the green channel over the whole RGB view of each class image [N]."""
        return np.take(GREEN_LEVELS, classes).mean(axis=(1, 2))

    def render(self, car: dict) -> np.ndarray:
        """uint8 RGB views [N, 3, 96, 96] of all copies (car states as for `classes`)."""
        return self.colours(self.classes(car, np.arange(len(car["x"]))))

    def _draw_hull(self, window: np.ndarray, tilt: np.ndarray) -> None:
        """The hull's polygons, turned by `tilt` [N] (the hull's angle in the view), into the car's
        windows [N, 24, 16] of the class images."""
        cos, sin = np.cos(tilt)[:, None], np.sin(tilt)[:, None]
        u = cos * self.hull_across + sin * self.hull_along  # the pixels in the hull's frame
        v = -sin * self.hull_across + cos * self.hull_along
        hull = np.zeros(u.shape, dtype=bool)
        for edges in self.hull_edges:
            hull |= _inside_convex(u, v, edges)
        rows, columns = self.hull_pixels
        window[:, rows, columns] = np.where(hull, HULL, window[:, rows, columns])

    def _draw_wheels(self, window: np.ndarray, car: dict, tilt: np.ndarray) -> None:
        """Each wheel as gymnasium draws it, into the car's windows [N, 24, 16] of the class images: a
        black rectangle at the wheel's pose (turned by `tilt` [N], the hull's angle in the view), then
        a grey stripe between heights R cos(phase) and R cos(phase + 1.2) while that part faces the
        viewer. Of the window's pixels only those of each wheel's block (see WHEEL_REACH) are tested:
        no other pixel's centre can be inside the wheel."""
        cos_tilt, sin_tilt = np.cos(tilt)[:, None], np.sin(tilt)[:, None]
        hull_x, hull_y = car["wheel_xy"][:, :, 0], car["wheel_xy"][:, :, 1]
        wheel_x = cos_tilt * hull_x - sin_tilt * hull_y  # the wheels' centres in the view's frame
        wheel_y = sin_tilt * hull_x + cos_tilt * hull_y
        # The block's first row and column: window row r's centre is (11.5 - r) * 0.514 units ahead of
        # the car's, column c's (c - 7.5) * 0.643 to its right. Parts of a block beyond the window
        # repeat its edge pixels (a pixel drawn twice is drawn the same).
        first_row = np.ceil((CAR_ROW - CAR_ROWS.start - 0.5) - (wheel_y + WHEEL_REACH) / UNITS_PER_PIXEL_Y)
        first_column = np.ceil((wheel_x - WHEEL_REACH) / UNITS_PER_PIXEL_X + (CAR_COLUMN - CAR_COLUMNS.start - 0.5))
        rows = np.clip(first_row.astype(np.int64)[..., None] + np.arange(WHEEL_BLOCK_ROWS), 0, window.shape[1] - 1)
        columns = np.clip(first_column.astype(np.int64)[..., None] + np.arange(WHEEL_BLOCK_COLUMNS), 0, window.shape[2] - 1)
        dx = self.car_across[0, columns][:, :, None, :] - wheel_x[:, :, None, None]  # [N, 4, 1, 2]
        dy = self.car_along[rows, 0][:, :, :, None] - wheel_y[:, :, None, None]  # [N, 4, 3, 1]
        angle = car["wheel_angle"] + tilt[:, None]
        cos, sin = np.cos(angle)[..., None, None], np.sin(angle)[..., None, None]
        u = dx * cos + dy * sin
        v = dy * cos - dx * sin
        across_wheel = np.abs(u) <= WHEEL_HALF_WIDTH
        wheel = across_wheel & (np.abs(v) <= WHEEL_HALF_LENGTH)
        phase = car["wheel_phase"]
        s1, s2 = np.sin(phase), np.sin(phase + 1.2)
        c1 = np.where(s1 > 0, np.sign(np.cos(phase)), np.cos(phase))
        c2 = np.where(s2 > 0, np.sign(np.cos(phase + 1.2)), np.cos(phase + 1.2))
        shown = ~((s1 > 0) & (s2 > 0))
        low = (np.minimum(c1, c2) * WHEEL_HALF_LENGTH)[..., None, None]
        high = (np.maximum(c1, c2) * WHEEL_HALF_LENGTH)[..., None, None]
        stripe = shown[..., None, None] & across_wheel & (v >= low) & (v <= high)
        pixels = np.broadcast_arrays(np.arange(len(window))[:, None, None, None], rows[:, :, :, None], columns[:, :, None, :])
        window[tuple(index[wheel] for index in pixels)] = WHEEL
        window[tuple(index[stripe] for index in pixels)] = WHEEL_STRIPE

    def _draw_indicators(self, classes: np.ndarray, car: dict) -> np.ndarray:
        """Gymnasium's bar, into the bottom rows [N, R, 96] of class images (R = 96: whole images):
        black bottom eighth; vertical bars (speed, ABS) rise from h above the bottom by h * value;
        horizontal bars (steering, gyroscope) extend from their place by s * value (s = h = 96 / 40
        pixels). Returns which copies [N] have a vertical bar reaching above the rows given."""
        unit = STATE_SIZE / 40.0
        bottom = STATE_SIZE
        top = STATE_SIZE - classes.shape[1]  # the first row given
        classes[:, BAR_TOP - top :, :] = BAR  # rows 84-95: centres inside [H - 5h, H]
        centres = self.bar_centres
        values = np.column_stack([0.02 * car["speed"], 0.01 * car["wheel_omega"]])  # [N, 5], in bar order
        base, tip = bottom - unit, bottom - unit - unit * values
        lit = (centres >= np.minimum(base, tip)[..., None]) & (centres <= np.maximum(base, tip)[..., None])  # [N, 5, rows]
        reaching_above = lit[:, :, :top].any(axis=(1, 2))
        lit = lit[:, self.vertical_bar, top:].transpose(0, 2, 1)  # [N, R, columns of the bars]
        classes[:, :, self.vertical_columns] = np.where(lit, self.vertical_classes, classes[:, :, self.vertical_columns])
        horizontal = [(20, -10.0 * car["steering"], STEERING), (30, -0.8 * car["angular_velocity"], GYROSCOPE)]
        band = classes[:, self.horizontal_rows.start - top : self.horizontal_rows.stop - top, :]
        for place, value, cls in horizontal:
            start, end = place * unit, (place + value) * unit
            lit = (centres >= np.minimum(start, end)[:, None]) & (centres <= np.maximum(start, end)[:, None])
            band[np.broadcast_to(lit[:, None, :], band.shape)] = cls
        return reaching_above
