"""CarRacing tracks: Bezier tracks from sketch cells or random control points, the F1 tracks, gymnasium's
own random track, three built-in held-out tracks, kerbs and track metrics. Pure geometry, no physics.

A track is a closed centreline in driving order: point k is followed by point k + 1 (and the last by
the first), the car starts on point 0 facing point 1. Each point also carries `beta`, the angle of the
road's cross direction: (cos beta, sin beta) points to the right of the driving direction and the car
starts with hull angle beta (gymnasium's convention: a hull at angle beta drives towards
(-sin beta, cos beta)). Tile k is the quad between the cross sections at points k - 1 and k, as
gymnasium builds it. Units are gymnasium's world units (SCALE 6).
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
import os
import pickle
import sys
import zipfile

import numpy as np

SCALE = 6.0  # gymnasium's track scale
TRACK_RAD = 900 / SCALE
PLAYFIELD = 2000 / SCALE  # half-size of the playfield of designed tracks and vanilla
F1_PLAYFIELD = 3000 / SCALE  # half-size for the F1 tracks (the reference's bounds of 3000)
TRACK_WIDTH = 40 / SCALE  # half-width of the road
TRACK_DETAIL_STEP = 21 / SCALE
TRACK_TURN_RATE = 0.31
BORDER = 8 / SCALE  # kerb width
BORDER_MIN_COUNT = 4
FPS = 50

SKETCH_SIZE = 10  # the teacher's 10x10 sketch grid
NUM_CONTROL_POINTS = 12
SKETCH_RATIO = PLAYFIELD / SKETCH_SIZE  # 33.33 world units per sketch cell
POINTS_PER_SEGMENT = 40
BEZIER_RAD = 0.2
BEZIER_EDGY = 0.2
MAX_POINT_REDRAWS = 200  # DR's control points: the reference's limit of redraws of a crowded set

DEFAULT_FRAME_LIMIT = 2000  # an F1 track without a frame limit in the meta json
VANILLA_FRAME_LIMIT = 1000


@dataclasses.dataclass
class Track:
    """One closed track: centreline xy [T, 2] in driving order, cross-direction angle beta [T], kerb
    flags [T] (tile k has a kerb), the kerb side [T] (+1 right, -1 left of the driving direction), the
    stripe colour of each kerb piece [T] (0 white, 1 red), and the playfield half-size."""

    xy: np.ndarray
    beta: np.ndarray
    kerb: np.ndarray
    kerb_side: np.ndarray
    stripe: np.ndarray
    playfield: float

    def __len__(self) -> int:
        return len(self.xy)


# ---------------------------------------------------------------------------------------------------
# Building a track from a centreline: cross directions, kerbs (gymnasium's rule, per unit of length).
# ---------------------------------------------------------------------------------------------------
def make_track(xy: np.ndarray, playfield: float, beta: np.ndarray | None = None) -> Track:
    """A Track from a closed centreline in driving order (the last point is not repeated). Points
    closer than 1e-9 to their predecessor are dropped (no zero-length tiles). Without `beta`, each
    point's cross direction is perpendicular to the step towards the next point."""
    xy = np.asarray(xy, dtype=np.float64)
    keep = np.linalg.norm(xy - np.roll(xy, 1, axis=0), axis=1) > 1e-9
    if beta is not None:
        beta = np.asarray(beta, dtype=np.float64)[keep]
    xy = xy[keep]
    if beta is None:
        step = np.roll(xy, -1, axis=0) - xy
        beta = np.arctan2(step[:, 1], step[:, 0]) - math.pi / 2
    kerb, side = kerb_flags(xy, beta)
    arc = arc_length(xy)
    stripe = (np.floor(arc / TRACK_DETAIL_STEP) % 2).astype(np.int8)
    return Track(xy, beta, kerb, side, stripe, float(playfield))


def arc_length(xy: np.ndarray) -> np.ndarray:
    """Distance along the track from point 0 to each point [T]."""
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def turning_angles(beta: np.ndarray) -> np.ndarray:
    """Signed turn from point k - 1 to point k [T] (wrapped to [-pi, pi); positive = left turn)."""
    return (beta - np.roll(beta, 1) + math.pi) % (2 * math.pi) - math.pi


def kerb_flags(xy: np.ndarray, beta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gymnasium's red-white border rule, measured per unit of length so that it does not depend on
    how finely a track is sampled: a point is on a sharp turn when the heading turned by more than
    0.2 * TRACK_TURN_RATE over each of the last BORDER_MIN_COUNT stretches of TRACK_DETAIL_STEP, all
    the same way; the kerb then also covers the BORDER_MIN_COUNT stretches before it. On gymnasium's
    own tracks (points TRACK_DETAIL_STEP apart) this is exactly its rule. The kerb lies on the inside
    of the turn, as gymnasium draws it. Returns (kerb [T] bool, side [T] +1 right / -1 left)."""
    count = len(xy)
    arc = arc_length(xy)
    total = arc[-1] + np.linalg.norm(xy[0] - xy[-1])
    heading = beta[0] + np.concatenate([[0.0], np.cumsum(turning_angles(beta)[1:])])
    winding = heading[-1] + turning_angles(beta)[0] - heading[0]
    arc_ext = np.concatenate([arc - total, arc, arc + total])
    heading_ext = np.concatenate([heading - winding, heading, heading + winding])
    turns = np.stack([np.interp(arc - k * TRACK_DETAIL_STEP, arc_ext, heading_ext) - np.interp(arc - (k + 1) * TRACK_DETAIL_STEP, arc_ext, heading_ext) for k in range(BORDER_MIN_COUNT)])
    sharp = np.all(np.abs(turns) > TRACK_TURN_RATE * 0.2, axis=0) & (np.abs(np.sign(turns).sum(axis=0)) == BORDER_MIN_COUNT)
    side = np.where(turns[0] > 0, -1, 1).astype(np.int8)  # gymnasium: side = sign(beta_prev - beta)
    # Spread each sharp point over the stretch of (BORDER_MIN_COUNT - 1) steps before it, around the loop.
    sharp_arc = np.sort(np.concatenate([arc[sharp] - total, arc[sharp], arc[sharp] + total]))
    reach = (BORDER_MIN_COUNT - 1) * TRACK_DETAIL_STEP + 1e-9
    kerb = np.searchsorted(sharp_arc, arc + reach, side="right") > np.searchsorted(sharp_arc, arc, side="left")
    # A kerb point inherits the side of the sharp point that marked it (the next sharp point ahead).
    sharp_index = np.nonzero(sharp)[0]
    if len(sharp_index):
        ahead = np.searchsorted(sharp_index, np.arange(count)) % len(sharp_index)
        side = np.where(sharp, side, side[sharp_index[ahead]])
    return kerb, side


# ---------------------------------------------------------------------------------------------------
# Bezier tracks from the teacher's sketch cells and from DR's random control points.
# ---------------------------------------------------------------------------------------------------
def cell_points(cells: np.ndarray) -> np.ndarray:
    """World points of sketch cells: cell a is column i = a % 10, row j = a // 10 of the sketch
    (sketch[j, i], so the flattened sketch is indexed by a) and lies at ((i + 1) * 33.33, (j + 1) * 33.33)."""
    cells = np.asarray(cells)
    return np.stack([(cells % SKETCH_SIZE + 1) * SKETCH_RATIO, (cells // SKETCH_SIZE + 1) * SKETCH_RATIO], axis=-1).astype(np.float64)


def sort_around_centroid(points: np.ndarray) -> np.ndarray:
    """The points in the reference's order around their centroid: ascending arctan2(dx, dy) (clockwise
    from due south), ties broken by the distance to the centroid, so the order never depends on the
    order the points came in (the caller passes them in a canonical order, making the centroid's
    floating-point value order-independent too)."""
    d = points - points.mean(axis=0)
    return points[np.lexsort((np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 0], d[:, 1])))]


def bezier_loop(points: np.ndarray, rad: float = BEZIER_RAD, edgy: float = BEZIER_EDGY, per_segment: int = POINTS_PER_SEGMENT) -> np.ndarray:
    """The reference's closed Bezier curve through `points` in the given order: each consecutive pair
    is a cubic segment whose inner control points lie rad * |p2 - p1| from the ends along a blended
    angle (edgy sets the blend), sampled at `per_segment` points (t = 0, 1/40, ..., 39/40; the end
    point is the next segment's start, so no point repeats). Returns [len(points) * per_segment, 2]."""
    closed = np.concatenate([points, points[:1]])
    step = np.diff(closed, axis=0)
    angle = np.arctan2(step[:, 1], step[:, 0]) % (2 * math.pi)
    blend = math.atan(edgy) / math.pi + 0.5
    previous = np.roll(angle, 1)
    angle = blend * angle + (1 - blend) * previous + (np.abs(previous - angle) > math.pi) * math.pi
    angle = np.append(angle, angle[0])
    reach = rad * np.linalg.norm(step, axis=1)[:, None]
    direction = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    control = np.stack([closed[:-1], closed[:-1] + reach * direction[:-1], closed[1:] - reach * direction[1:], closed[1:]], axis=1)
    t = (np.arange(per_segment) / per_segment)[:, None]
    weights = np.stack([(1 - t) ** 3, 3 * t * (1 - t) ** 2, 3 * t**2 * (1 - t), t**3], axis=1)  # [P, 4, 1]
    curve = np.einsum("pkx,skd->spd", weights, control)
    return curve.reshape(-1, 2)


def centre_on_bounding_box(xy: np.ndarray) -> np.ndarray:
    """The points shifted so that their bounding box is centred on the origin (as the reference)."""
    return xy - (xy.min(axis=0) + xy.max(axis=0)) / 2


def reference_driving_order(xy: np.ndarray) -> np.ndarray:
    """The reference places the car facing against the order of the curve's points (hull angle
    pi/2 + the step's angle), so it drives the points backwards from point 0: return them in that
    order, so that the car here starts on the same point and drives the same way, facing forwards."""
    return np.roll(xy[::-1], 1, axis=0)


def track_from_unordered_points(points: np.ndarray) -> Track:
    """The reference's Bezier track through control points given in any order: sorted around their
    centroid, closed Bezier loop (12 * 40 points), driving order as the reference's, centred on the
    bounding box. A repeated point makes a segment of length 0, whose points make_track drops."""
    return make_track(centre_on_bounding_box(reference_driving_order(bezier_loop(sort_around_centroid(points)))), PLAYFIELD)


def track_from_cells(cells: np.ndarray) -> Track:
    """The designed track of 12 sketch cells (any order; a cell may repeat, as in the levels of the
    reference's random teacher), through their world points."""
    cells = np.sort(np.asarray(cells))
    if cells.shape != (NUM_CONTROL_POINTS,) or cells[0] < 0 or cells[-1] >= SKETCH_SIZE**2 or len(np.unique(cells)) < 3:
        raise ValueError(f"a designed track needs {NUM_CONTROL_POINTS} sketch cells in [0, {SKETCH_SIZE**2}), "
                         f"at least 3 of them different, got {cells.tolist()}")
    return track_from_unordered_points(cell_points(cells))


def random_control_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """n sets of 12 control points [n, 12, 2] for DR's tracks, drawn as the reference implementation
    (dcd) draws them (bezier.get_random_points with scale = playfield): uniform in the unit square,
    the whole set drawn again while two neighbours in the order around the centroid are closer than
    0.7 / 12 by the reference's measure |dx + dy| (its formula, not the Euclidean distance; the last
    point's step back to the first is not checked), at most 200 times (the 201st draw is kept as it is),
    then scaled to [0, PLAYFIELD)."""
    points = rng.random((n, NUM_CONTROL_POINTS, 2))
    for _ in range(MAX_POINT_REDRAWS):
        crowded = ~well_spaced(points)
        if not crowded.any():
            break
        points[crowded] = rng.random((int(crowded.sum()), NUM_CONTROL_POINTS, 2))
    return points * PLAYFIELD


def well_spaced(points: np.ndarray) -> np.ndarray:
    """For point sets [n, P, 2]: every step between neighbours around the centroid has |dx + dy| >=
    0.7 / P (the reference's test in bezier.get_random_points), per set [n]."""
    d = points - points.mean(axis=1, keepdims=True)
    order = np.argsort(np.arctan2(d[..., 0], d[..., 1]), axis=1)
    ordered = np.take_along_axis(points, order[..., None], axis=1)
    return np.all(np.abs(np.diff(ordered, axis=1).sum(axis=2)) >= 0.7 / points.shape[1], axis=1)


def track_from_centreline(xy: np.ndarray, playfield: float = F1_PLAYFIELD) -> Track:
    """A fixed track (F1) from its closed centreline points, used as-is, centred on the bounding box and
    driven against the points' order as the reference does (clockwise for the counter-clockwise F1 files)."""
    return make_track(centre_on_bounding_box(reference_driving_order(np.asarray(xy, dtype=np.float64))), playfield)


def track_from_control_points(points) -> Track:
    """A built-in track from hand-placed control points, kept in the given (driving) order."""
    return make_track(centre_on_bounding_box(bezier_loop(np.asarray(points, dtype=np.float64))), PLAYFIELD)


# ---------------------------------------------------------------------------------------------------
# Gymnasium's own random track ("vanilla"), its generation logic ported without rendering.
# ---------------------------------------------------------------------------------------------------
def vanilla_track(rng: np.random.Generator) -> Track:
    """Gymnasium CarRacing's random track, drawn from rng (retried until a loop closes, as gymnasium)."""
    while True:
        track = _vanilla_attempt(rng)
        if track is not None:
            return track


def _vanilla_attempt(rng: np.random.Generator) -> Track | None:
    """One try of gymnasium's CarRacing._create_track (same constants and steps); None if it fails."""
    checkpoint_count = 12
    checkpoints = []
    for c in range(checkpoint_count):
        noise = rng.uniform(0, 2 * math.pi * 1 / checkpoint_count)
        alpha = 2 * math.pi * c / checkpoint_count + noise
        rad = rng.uniform(TRACK_RAD / 3, TRACK_RAD)
        if c == 0:
            alpha = 0
            rad = 1.5 * TRACK_RAD
        if c == checkpoint_count - 1:
            alpha = 2 * math.pi * c / checkpoint_count
            rad = 1.5 * TRACK_RAD
        checkpoints.append((alpha, rad * math.cos(alpha), rad * math.sin(alpha)))
    start_alpha = 2 * math.pi * (-0.5) / checkpoint_count

    x, y, beta = 1.5 * TRACK_RAD, 0, 0
    dest_i, laps, no_freeze, visited_other_side = 0, 0, 2500, False
    track = []
    while True:
        alpha = math.atan2(y, x)
        if visited_other_side and alpha > 0:
            laps += 1
            visited_other_side = False
        if alpha < 0:
            visited_other_side = True
            alpha += 2 * math.pi
        while True:  # find the destination checkpoint
            failed = True
            while True:
                dest_alpha, dest_x, dest_y = checkpoints[dest_i % len(checkpoints)]
                if alpha <= dest_alpha:
                    failed = False
                    break
                dest_i += 1
                if dest_i % len(checkpoints) == 0:
                    break
            if not failed:
                break
            alpha -= 2 * math.pi
        r1x, r1y = math.cos(beta), math.sin(beta)
        p1x, p1y = -r1y, r1x
        proj = r1x * (dest_x - x) + r1y * (dest_y - y)
        while beta - alpha > 1.5 * math.pi:
            beta -= 2 * math.pi
        while beta - alpha < -1.5 * math.pi:
            beta += 2 * math.pi
        prev_beta = beta
        proj *= SCALE
        if proj > 0.3:
            beta -= min(TRACK_TURN_RATE, abs(0.001 * proj))
        if proj < -0.3:
            beta += min(TRACK_TURN_RATE, abs(0.001 * proj))
        x += p1x * TRACK_DETAIL_STEP
        y += p1y * TRACK_DETAIL_STEP
        track.append((alpha, prev_beta * 0.5 + beta * 0.5, x, y))
        if laps > 4:
            break
        no_freeze -= 1
        if no_freeze == 0:
            break

    i1, i2 = -1, -1  # closed loop range i1..i2: the first lap is ignored, the second is kept
    i = len(track)
    while True:
        i -= 1
        if i == 0:
            return None
        through_start = track[i][0] > start_alpha and track[i - 1][0] <= start_alpha
        if through_start and i2 == -1:
            i2 = i
        elif through_start and i1 == -1:
            i1 = i
            break
    track = np.array(track[i1 : i2 - 1])
    first_beta = track[0, 1]
    glue = math.hypot(math.cos(first_beta) * (track[0, 2] - track[-1, 2]), math.sin(first_beta) * (track[0, 3] - track[-1, 3]))
    if glue > TRACK_DETAIL_STEP:
        return None
    return make_track(track[:, 2:4], PLAYFIELD, beta=track[:, 1])


# ---------------------------------------------------------------------------------------------------
# Built-in held-out tracks (used when no F1 file is given): hand-placed control points, driving order.
# ---------------------------------------------------------------------------------------------------
BUILTIN_TRACKS = {
    # Four hairpins: a serpentine of three narrow switchbacks and a long return straight.
    "Hairpins": [
        (-250, -230),
        (250, -230),
        (270, 180),
        (190, 200),
        (150, -80),
        (90, -90),
        (50, 180),
        (-30, 200),
        (-70, -80),
        (-130, -90),
        (-170, 180),
        (-250, 200),
        (-280, 0),
    ],
    # An oval whose two straights each carry two S-bends.
    "Chicanes": [
        (-270, -150),
        (-140, -150),
        (-100, -110),
        (-60, -150),
        (60, -150),
        (100, -190),
        (140, -150),
        (270, -150),
        (290, 0),
        (270, 150),
        (140, 150),
        (100, 110),
        (60, 150),
        (-60, 150),
        (-100, 190),
        (-140, 150),
        (-270, 150),
        (-290, 0),
    ],
    # A long thin loop: two 550-unit straights joined by fast sweepers.
    "LongStraights": [(-280, -110), (0, -115), (280, -110), (310, 0), (280, 110), (0, 115), (-280, 110), (-310, 0)],
}
BUILTIN_FRAME_LIMITS = {"Hairpins": 2500, "Chicanes": 1800, "LongStraights": 1500}  # ~1 frame per unit of length


# ---------------------------------------------------------------------------------------------------
# The F1 track file: .npz of name -> (N, 2) closed centreline, <stem>_meta.json beside it.
# ---------------------------------------------------------------------------------------------------
_F1_CACHE: dict = {}


def load_f1_tracks(path: str) -> dict[str, tuple[np.ndarray, int]]:
    """name -> (centreline points float64 [N, 2], frame limit) from an F1 track file.

    The file is an .npz of name -> (N, 2) closed centreline points in world units (used as-is; the
    track builder centres them). Frame limits come from `<stem>_meta.json` beside it
    ({name: {"max_episode_frames": int, ...}}), 2000 frames for a track it does not list or if it is
    absent. Raises ValueError with a one-line message for a missing or malformed file."""
    if not os.path.isfile(path):
        raise ValueError(f"F1 track file {path!r} does not exist")
    stamp = (os.path.abspath(path), os.path.getmtime(path))
    if stamp in _F1_CACHE:
        return _F1_CACHE[stamp]
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.array(data[name]) for name in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError) as error:
        raise ValueError(f"F1 track file {path!r} is not a readable .npz file ({type(error).__name__})") from None
    if not arrays:
        raise ValueError(f"F1 track file {path!r} holds no tracks")
    limits = _read_frame_limits(os.path.splitext(path)[0] + "_meta.json")
    tracks = {}
    for name, xy in sorted(arrays.items()):
        if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < 3 or not np.issubdtype(xy.dtype, np.number) or not np.all(np.isfinite(xy)):
            raise ValueError(f"F1 track {name!r} in {path!r} is not an (N >= 3, 2) array of finite numbers")
        tracks[name] = (xy.astype(np.float64), int(limits.get(name, DEFAULT_FRAME_LIMIT)))
    _F1_CACHE[stamp] = tracks
    return tracks


def _read_frame_limits(meta_path: str) -> dict[str, int]:
    """name -> max_episode_frames from a meta json; {} when there is no such file."""
    if not os.path.isfile(meta_path):
        return {}
    try:
        with open(meta_path) as f:
            meta = json.load(f)
        limits = {name: int(entry["max_episode_frames"]) for name, entry in meta.items()}
    except (ValueError, TypeError, KeyError, AttributeError) as error:
        raise ValueError(f"F1 meta file {meta_path!r} is malformed ({type(error).__name__}: {error})") from None
    if any(limit <= 0 for limit in limits.values()):
        raise ValueError(f"F1 meta file {meta_path!r} has a non-positive max_episode_frames")
    return limits


def convert_formula1(source_path: str, out_path: str) -> list[str]:
    """Convert the reference implementation's formula1.py (assignments `Name = RaceTrack(name=...,
    xy=[[x, y], ...], bounds=..., full_zoom=..., max_episode_steps=...)`) to an .npz of name -> xy and
    its `<stem>_meta.json`. The file is parsed, never executed. Returns the track names."""
    try:
        with open(source_path) as f:
            tree = ast.parse(f.read(), filename=source_path)
    except (OSError, SyntaxError) as error:
        raise ValueError(f"cannot read {source_path!r} as Python source ({type(error).__name__})") from None
    tracks, meta = {}, {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "RaceTrack":
            fields = {k.arg: ast.literal_eval(k.value) for k in node.keywords}
            if "name" not in fields or "xy" not in fields:
                raise ValueError(f"a RaceTrack in {source_path!r} lacks name= or xy=")
            xy = np.asarray(fields["xy"], dtype=np.float32)
            tracks[fields["name"]] = xy
            meta[fields["name"]] = {
                "max_episode_frames": int(fields.get("max_episode_steps", DEFAULT_FRAME_LIMIT)),
                "bounds": fields.get("bounds", 3000),
                "full_zoom": fields.get("full_zoom", 0.12),
                "n_points": len(xy),
            }
    if not tracks:
        raise ValueError(f"no RaceTrack(...) definitions found in {source_path!r}")
    np.savez_compressed(out_path, **tracks)
    with open(out_path.removesuffix(".npz") + "_meta.json", "w") as f:
        json.dump(meta, f, indent=1)
    return sorted(tracks)


# ---------------------------------------------------------------------------------------------------
# Track metrics (for the curriculum plots).
# ---------------------------------------------------------------------------------------------------
def track_metrics(track: Track) -> tuple[float, float, int]:
    """(length, total curvature = sum of absolute turning angles, sharp turns = kerb stretches)."""
    length = float(arc_length(np.concatenate([track.xy, track.xy[:1]]))[-1])
    curvature = float(np.abs(turning_angles(track.beta)).sum())
    kerb = track.kerb
    sharp_turns = int(np.sum(kerb & ~np.roll(kerb, 1))) if not kerb.all() else 1
    return length, curvature, sharp_turns


def main(argv=None) -> None:
    """python -m envs.carracing.tracks convert formula1.py out.npz: the reference's formula1.py (a Python file
    of RaceTrack(name=..., xy=[...]) definitions, parsed, not run) to an .npz and its _meta.json."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 3 or args[0] != "convert":
        print("usage: python -m envs.carracing.tracks convert formula1.py out.npz", file=sys.stderr)
        sys.exit(2)
    try:
        names = convert_formula1(args[1], args[2])
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    print(f"wrote {len(names)} tracks to {args[2]}: {', '.join(names)}")


if __name__ == "__main__":
    main()
