"""Reader of RGB-D sequences in the TUM layout: ``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt`` and
``accelerometer.txt``.

Colour and depth are associated by nearest timestamp (greedy, as TUM's ``associate.py``); frames load
lazily, one at a time, so a sequence of any length costs the memory of a frame.
"""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path

import cv2
import numpy as np
import PIL.Image

from tambridge.camera import Camera, RgbdSensor, find_sensor
from tambridge.errors import SequenceFormatError
from tambridge.files import read_text_file
from tambridge.io.image_folders import find_image_folders
from tambridge.io.registration import ColourToDepth
from tambridge.trajectory import Trajectory, read_tum_trajectory

MAX_ASSOCIATION_DIFFERENCE_S = 0.02
PLAUSIBLE_MEDIAN_DEPTH_M = (0.1, 10.0)
MAX_SATURATED_SHARE = 0.01
"""Share of a depth image's pixels at 65535 from which, with no ``depth_invalid`` given, the reader asks whether that
value marks missing depth."""
GT_RGB_FOLDER = "gt_rgb"
"""Optional folder of sharp ground-truth colour images, named as in ``rgb/`` (synthetic blurred sequences)."""


@dataclasses.dataclass
class Frame:
    """One RGB-D frame: ``rgb`` (H, W, 3) uint8, ``depth_m`` (H, W) float32 metres (0 = invalid).

    ``timestamp_s`` is the colour image's time, the frame's; ``depth_timestamp_s`` the depth image's, where the
    sensor took it at another time (TUM: up to 20 ms apart), None where both were taken together.
    """

    index: int
    timestamp_s: float
    rgb: np.ndarray
    depth_m: np.ndarray
    depth_timestamp_s: float | None = None

    @property
    def depth_delay_s(self) -> float:
        """``depth_timestamp_s - timestamp_s`` in seconds (0 where depth and colour were taken together)."""
        return 0.0 if self.depth_timestamp_s is None else self.depth_timestamp_s - self.timestamp_s


def read_file_list(path: Path) -> list[tuple[float, str]]:
    """Parse a TUM ``timestamp filename`` list (UTF-8), sorted by timestamp; errors name the file and line.

    A file name may hold spaces where the whole rest of the line names an existing file; otherwise words after the
    file name are ignored, as TUM's tools do. A timestamp listed twice is refused: each frame must be listed once.
    """
    if not path.is_file():
        if path.is_dir():
            raise SequenceFormatError(f"{path}: is a folder; expected a text file of 'timestamp filename' lines")
        raise SequenceFormatError(
            f"{path}: not found; a TUM sequence folder needs rgb.txt and depth.txt "
            "(lines of 'timestamp filename'), as in the TUM RGB-D downloads"
        )
    entries = []
    first_line_of: dict[float, int] = {}
    for number, line in enumerate(read_text_file(path, SequenceFormatError).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise SequenceFormatError(f"{path} line {number}: expected 'timestamp filename', got {line!r}")
        try:
            timestamp = float(parts[0])
        except ValueError:
            raise SequenceFormatError(f"{path} line {number}: timestamp {parts[0]!r} is not a number") from None
        if not np.isfinite(timestamp):
            raise SequenceFormatError(f"{path} line {number}: timestamp {parts[0]!r} is not finite")
        if timestamp in first_line_of:
            raise SequenceFormatError(f"{path} line {number}: timestamp {parts[0]} is already listed on line "
                                      f"{first_line_of[timestamp]}; list each frame once")
        first_line_of[timestamp] = number
        name = line[len(parts[0]):].strip()
        entries.append((timestamp, name if len(parts) > 2 and (path.parent / name).is_file() else parts[1]))
    if not entries:
        raise SequenceFormatError(f"{path}: lists no images")
    entries.sort(key=lambda entry: entry[0])
    return entries


def associate(
    timestamps_a: np.ndarray, timestamps_b: np.ndarray, max_difference_s: float = MAX_ASSOCIATION_DIFFERENCE_S
) -> list[tuple[int, int]]:
    """Index pairs (i, j) with ``|a_i - b_j| < max_difference_s``, greedy by smallest difference, each index once.

    This is the matching of TUM's ``associate.py`` (offset 0); pairs are returned sorted by ``a``.
    """
    timestamps_a = np.asarray(timestamps_a, float)
    timestamps_b = np.asarray(timestamps_b, float)
    candidates = []
    for i, stamp in enumerate(timestamps_a):
        low = np.searchsorted(timestamps_b, stamp - max_difference_s, side="left")
        high = np.searchsorted(timestamps_b, stamp + max_difference_s, side="right")
        for j in range(low, high):
            difference = abs(stamp - timestamps_b[j])
            if difference < max_difference_s:
                candidates.append((difference, i, j))
    candidates.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def inscribed_rectangle(valid: np.ndarray) -> tuple[int, int, int, int]:
    """``(top, bottom, left, right)``: an axis-aligned box of (H, W) bool ``valid`` holding only True pixels.

    Undistortion leaves a border of pixels that sample outside the raw image (black in colour, 0 in depth): on
    TUM fr1 5 % of the frame. Starting from the whole frame, the side with the most invalid pixels is moved in one
    row or column at a time (the side with the largest share of invalid pixels) until none is left; for the
    convex valid region of a lens this comes close to the largest box.
    """
    top, bottom, left, right = 0, valid.shape[0], 0, valid.shape[1]
    while top < bottom and left < right:
        box = valid[top:bottom, left:right]
        missing = {"top": 1 - box[0].mean(), "bottom": 1 - box[-1].mean(), "left": 1 - box[:, 0].mean(),
                   "right": 1 - box[:, -1].mean()}
        side = max(missing, key=missing.get)
        if missing[side] == 0:
            break
        if side == "top":
            top += 1
        elif side == "bottom":
            bottom -= 1
        elif side == "left":
            left += 1
        else:
            right -= 1
    return top, bottom, left, right


class RgbdSequence:
    """A TUM-layout RGB-D sequence: associated frames loaded on access, undistorted where the camera says.

    ``camera`` is the camera of the frames this class returns (distortion removed). A sensor with an unregistered
    colour camera gives frames in its depth camera, colour resampled into it.
    """

    def __init__(
        self,
        folder: Path,
        sensor: RgbdSensor,
        rgb_paths: list[Path],
        depth_paths: list[Path],
        timestamps_s: np.ndarray,
        ground_truth: Trajectory | None,
        gt_rgb_paths: list[Path] | None = None,
        depth_timestamps_s: np.ndarray | None = None,
        colour_images_without_depth: int = 0,
        colour_images_listed: int = 0,
    ) -> None:
        self.folder = folder
        # Colour images of rgb.txt that no depth image lies near (MAX_ASSOCIATION_DIFFERENCE_S): left out; of
        # colour_images_listed in rgb.txt (before stride and max_frames).
        self.colour_images_without_depth = colour_images_without_depth
        self.colour_images_listed = colour_images_listed
        self.sensor = sensor
        self.rgb_paths = rgb_paths
        # Sharp ground-truth colour images, one per frame (``gt_rgb/``), or None: see :meth:`sharp_rgb`.
        self.gt_rgb_paths = gt_rgb_paths
        self.depth_paths = depth_paths
        self.timestamps_s = timestamps_s
        # The depth images' own times (N,), or None where they are the colour images' (``timestamps_s``).
        self.depth_timestamps_s = depth_timestamps_s
        self.ground_truth = ground_truth
        self.camera: Camera = sensor.camera.undistorted()
        self._undistort_maps = None
        self._colour_to_depth = None
        # Rows top:bottom, columns left:right of the frames in which every pixel has data.
        self.valid_region: tuple[int, int, int, int] = (0, self.camera.height, 0, self.camera.width)
        if sensor.colour_camera is not None:
            self._colour_to_depth = ColourToDepth(sensor.camera, sensor.colour_camera, sensor.colour_from_depth)
            self.valid_region = inscribed_rectangle(self._colour_to_depth.inside_colour_image())
        elif sensor.camera.has_distortion:
            source = sensor.camera
            self._undistort_maps = cv2.initUndistortRectifyMap(
                source.K, np.array(source.distortion), None, source.K, (source.width, source.height), cv2.CV_32FC1
            )
            map_x, map_y = self._undistort_maps
            inside = (map_x >= 0) & (map_x <= source.width - 1) & (map_y >= 0) & (map_y <= source.height - 1)
            self.valid_region = inscribed_rectangle(inside)

    def __len__(self) -> int:
        return len(self.timestamps_s)

    def __getitem__(self, index: int) -> Frame:
        if not 0 <= index < len(self):
            raise IndexError(index)
        rgb = self.read_rgb(self.rgb_paths[index])
        depth_m = self.read_depth_m(self.depth_paths[index])
        rgb = self._colour_in_frame(rgb, self.rgb_paths[index], depth_m, self.depth_paths[index])
        depth_m = self._depth_in_frame(depth_m)
        depth_stamp = None if self.depth_timestamps_s is None else float(self.depth_timestamps_s[index])
        return Frame(index=index, timestamp_s=float(self.timestamps_s[index]), rgb=rgb, depth_m=depth_m,
                     depth_timestamp_s=depth_stamp)

    def frame_depth_m(self, index: int) -> np.ndarray:
        """Frame ``index``'s depth (H, W) metres alone, as ``self[index].depth_m`` (undistorted), without its colour."""
        return self._depth_in_frame(self.read_depth_m(self.depth_paths[index]))

    def _depth_in_frame(self, depth_m: np.ndarray) -> np.ndarray:
        """The depth image as read, undistorted where the camera has distortion."""
        if self._undistort_maps is None:
            return depth_m
        # Nearest neighbour: blending depth across an edge invents surfaces that do not exist.
        return cv2.remap(depth_m, *self._undistort_maps, cv2.INTER_NEAREST)

    @property
    def has_sharp_rgb(self) -> bool:
        """Whether the folder holds sharp ground-truth colour images (``gt_rgb/``, synthetic blurred sequences)."""
        return self.gt_rgb_paths is not None

    def sharp_rgb(self, index: int) -> np.ndarray:
        """Frame ``index``'s sharp ground-truth colour (H, W, 3) uint8 from ``gt_rgb/``, in the frames' camera as
        ``self[index].rgb`` is (registered, undistorted); only where :attr:`has_sharp_rgb`."""
        if self.gt_rgb_paths is None:
            raise SequenceFormatError(f"{self.folder}: no {GT_RGB_FOLDER}/ folder of sharp colour images")
        rgb = self.read_rgb(self.gt_rgb_paths[index])
        depth_m = self.read_depth_m(self.depth_paths[index]) if self._colour_to_depth is not None else None
        return self._colour_in_frame(rgb, self.gt_rgb_paths[index], depth_m, self.depth_paths[index])

    def _colour_in_frame(self, rgb: np.ndarray, rgb_path: Path, depth_m: np.ndarray | None, depth_path: Path) -> np.ndarray:
        """Colour ``rgb`` read from ``rgb_path`` as frames carry it: resampled into the depth camera (with the raw
        ``depth_m``, needed only then) or undistorted; sizes checked against the depth image of ``depth_path``."""
        if depth_m is not None:
            self._check_depth_size(depth_path, depth_m.shape[::-1], rgb_path, rgb.shape[1::-1])
        if self._colour_to_depth is not None:
            rgb = self._colour_to_depth.colour_in_depth_camera(rgb, depth_m)
        if self._undistort_maps is not None:
            rgb = cv2.remap(rgb, *self._undistort_maps, cv2.INTER_LINEAR)
        return rgb

    def __iter__(self):
        for index in range(len(self)):
            yield self[index]

    def read_rgb(self, path: Path) -> np.ndarray:
        """Colour image as (H, W, 3) uint8 RGB, checked against the camera size."""
        image = _imread(path, cv2.IMREAD_COLOR, "rgb.txt")
        if image.dtype != np.uint8:
            raise SequenceFormatError(f"{path}: colour image must be 8-bit, got {image.dtype}")
        self._check_colour_size(path, image.shape[1], image.shape[0])
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def _check_colour_size(self, path: Path, width: int, height: int) -> None:
        """Raise :class:`SequenceFormatError` naming ``path`` and the keys to fix unless a ``width`` x ``height``
        colour image fits the (colour) camera."""
        camera = self.sensor.colour_camera or self.sensor.camera
        if (width, height) != (camera.width, camera.height):
            keys = "colour_width/colour_height" if self.sensor.colour_camera else "width/height"
            # The first frame is read before a run starts (check_first_frame): a later one that fails here is
            # most likely the odd one out.
            raise SequenceFormatError(
                f"{path}: image is {width}x{height} but the camera is {camera.width}x{camera.height}; "
                f"fix {keys} in camera.yaml (--camera), or this image if the sequence's others are "
                f"{camera.width}x{camera.height}"
            )

    def _check_depth_size(self, depth_path: Path, depth_size: tuple[int, int], rgb_path: Path,
                          rgb_size: tuple[int, int]) -> None:
        """Raise :class:`SequenceFormatError` naming ``depth_path`` unless a depth image of ``depth_size`` (width,
        height) fits the depth camera (unregistered colour) or its colour image of ``rgb_size`` (registered)."""
        if self._colour_to_depth is not None:
            if depth_size != (self.camera.width, self.camera.height):
                raise SequenceFormatError(
                    f"{depth_path}: depth is {depth_size[0]}x{depth_size[1]} but the depth camera is "
                    f"{self.camera.width}x{self.camera.height}; fix width/height in camera.yaml (--camera)"
                )
        elif depth_size != rgb_size:
            raise SequenceFormatError(
                f"{depth_path}: depth is {depth_size[0]}x{depth_size[1]} but its colour image {rgb_path.name} is "
                f"{rgb_size[0]}x{rgb_size[1]}; colour and depth must be registered"
            )

    def check_frame_headers(self) -> None:
        """Every frame's colour and depth image, from its header alone (no decoding): the colour size, the depth's
        format (one 16-bit channel) and size, so that an odd frame anywhere fails before a run starts, naming the
        image, not when the run reaches it. Images whose header Pillow cannot read are left to decoding."""
        for rgb_path, depth_path in zip(self.rgb_paths, self.depth_paths):
            rgb, depth = image_header(rgb_path), image_header(depth_path)
            # Colour is decoded turned as a JPEG's EXIF orientation says (a phone's); depth as stored.
            rgb_size = None if rgb is None else rgb.size[::-1] if rgb.quarter_turned else rgb.size
            if rgb_size is not None:
                self._check_colour_size(rgb_path, *rgb_size)
            if depth is not None:
                if depth.mode not in SIXTEEN_BIT_GREY_MODES or (depth.mode == "I" and depth.format != "PNG"):
                    raise depth_format_error(depth_path, IMAGE_MODE_WORDS.get(depth.mode, f"Pillow mode {depth.mode}"))
                if rgb_size is not None:
                    self._check_depth_size(depth_path, depth.size, rgb_path, rgb_size)

    def read_depth_m(self, path: Path) -> np.ndarray:
        """Depth PNG (uint16) as (H, W) float32 metres, 0 where invalid."""
        raw = _imread(path, cv2.IMREAD_UNCHANGED, "depth.txt")
        if raw.ndim != 2 or raw.dtype != np.uint16:
            raise depth_format_error(path, f"{raw.dtype} with shape {raw.shape}")
        depth_m = raw.astype(np.float32) / np.float32(self.sensor.depth_scale)
        if self.sensor.depth_invalid is not None:
            depth_m[raw == self.sensor.depth_invalid] = 0.0
        return depth_m


JPEG_START = b"\xff\xd8"
JPEG_END = b"\xff\xd9"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_START = PNG_SIGNATURE[:4]
PNG_END = b"IEND"


def check_image_file(path: Path, listed_in: str) -> None:
    """Raise :class:`SequenceFormatError` naming ``path`` and the fix unless it is a non-empty file that ends as its
    format says (JPEG's end marker, PNG's IEND chunk): a stat and two short reads, no decoding, so that a whole
    sequence is checked before any work starts."""
    if path.is_dir():
        raise SequenceFormatError(f"{path}: listed in {listed_in} but is a folder, not an image; fix {listed_in}")
    if not path.is_file():
        raise SequenceFormatError(f"{path}: image listed in {listed_in} does not exist; fix {listed_in} or restore the file")
    size = path.stat().st_size
    if size == 0:
        raise SequenceFormatError(f"{path}: empty file; re-extract the sequence")
    with open(path, "rb") as handle:
        start = handle.read(len(PNG_START))
        handle.seek(max(0, size - 64))
        tail = handle.read()
    # libjpeg decodes a truncated file into a half-grey image with only a warning: check the end marker.
    if start[:2] == JPEG_START and JPEG_END not in tail:
        raise SequenceFormatError(f"{path}: JPEG has no end marker (truncated); re-extract the sequence")
    if start == PNG_START and PNG_END not in tail:
        raise SequenceFormatError(f"{path}: PNG has no IEND chunk (truncated); re-extract the sequence")


def check_png_checksums(path: Path) -> None:
    """Raise :class:`SequenceFormatError` naming ``path`` and the fix where a PNG's signature is damaged or its chunks
    up to IEND are cut short or fail their CRC-32: a bit flipped anywhere up to IEND, which the checks of
    :func:`check_image_file` miss and decoding meets only when the run reaches the frame. Reads the whole file,
    decodes nothing; other formats pass. Damage under checksums that fit (a deflate stream written wrong) is left
    to decoding."""
    data = memoryview(path.read_bytes())
    if data[:len(PNG_SIGNATURE)] != PNG_SIGNATURE:
        # The signature has no checksum: a PNG whose signature took the flip still has "PNG" or its IHDR chunk.
        if data[1:4] == b"PNG" or data[12:16] == b"IHDR":
            raise SequenceFormatError(f"{path}: PNG signature damaged (corrupt); re-extract the sequence")
        return
    position = len(PNG_SIGNATURE)
    while True:
        if position + 8 > len(data):
            raise SequenceFormatError(f"{path}: PNG ends inside a chunk header (truncated); re-extract the sequence")
        length = int.from_bytes(data[position:position + 4], "big")
        name = bytes(data[position + 4:position + 8])
        end = position + 8 + length
        if end + 4 > len(data):
            raise SequenceFormatError(f"{path}: PNG chunk {name.decode('latin-1')!r} is cut short (truncated); "
                                      "re-extract the sequence")
        if zlib.crc32(data[position + 4:end]) != int.from_bytes(data[end:end + 4], "big"):
            raise SequenceFormatError(f"{path}: PNG chunk {name.decode('latin-1')!r} fails its checksum (corrupt); "
                                      "re-extract the sequence")
        if name == PNG_END:
            return
        position = end + 4


SIXTEEN_BIT_GREY_MODES = ("I;16", "I;16B", "I;16L", "I")
"""Pillow's modes of a single-channel 16-bit image, the one depth format the reader takes (Pillow before 10 opens a
16-bit grey PNG as ``I``: that mode is taken from PNGs only, another format's ``I`` being 32-bit)."""
EXIF_ORIENTATION_TAG = 0x0112
EXIF_QUARTER_TURNS = (5, 6, 7, 8)
"""EXIF orientations that turn the image by a quarter (with or without a mirror): width and height swap."""
IMAGE_MODE_WORDS = {"1": "a 1-bit image", "L": "an 8-bit grey image", "LA": "an 8-bit grey image with alpha",
                    "P": "a palette image", "RGB": "a colour image", "RGBA": "a colour image with alpha",
                    "F": "a 32-bit float image"}
"""Pillow's image modes in words, for errors."""


@dataclasses.dataclass(frozen=True)
class ImageHeader:
    """What an image file's header says: ``size`` (width, height) as stored, Pillow's ``mode`` and ``format``, and
    whether a JPEG's EXIF orientation turns it by a quarter (cv2's colour decoding applies it)."""

    size: tuple[int, int]
    mode: str
    format: str | None
    quarter_turned: bool


def image_header(path: Path) -> ImageHeader | None:
    """The header of the image at ``path`` (no decoding); None where Pillow does not know the format."""
    try:
        with PIL.Image.open(path) as image:
            # A JPEG's EXIF sits before its pixels; other formats' would make Pillow decode the image to find it.
            turned = image.format == "JPEG" and image.getexif().get(EXIF_ORIENTATION_TAG) in EXIF_QUARTER_TURNS
            return ImageHeader(image.size, image.mode, image.format, turned)
    except (PIL.UnidentifiedImageError, OSError):
        return None


def depth_format_error(path: Path, got: str) -> SequenceFormatError:
    """The one-line error for a depth image at ``path`` that is not one 16-bit channel (``got``: what it is)."""
    return SequenceFormatError(f"{path}: depth must be a single-channel 16-bit PNG, got {got}; 8-bit or colour depth "
                               "loses the range (re-export depth as uint16)")


def _imread(path: Path, flags: int, listed_in: str) -> np.ndarray:
    """Decode an image by its content (whatever its extension); errors name the file and the fix."""
    check_image_file(path, listed_in)
    image = cv2.imread(str(path), flags)
    if image is None or image.size == 0:
        raise SequenceFormatError(f"{path}: cannot decode image (corrupt, truncated or not an image); re-extract the sequence")
    return image


def check_sequence_folder(folder: Path) -> None:
    """Raise :class:`SequenceFormatError` unless ``folder`` is a folder with TUM's rgb.txt or depth.txt (a stat or
    two; :func:`open_sequence` checks the rest)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SequenceFormatError(f"{folder}: not a folder; pass a TUM RGB-D sequence folder (with rgb.txt, depth.txt)")
    if not (folder / "rgb.txt").is_file() and not (folder / "depth.txt").is_file():
        if (folder / "associations.txt").is_file():
            raise SequenceFormatError(
                f"{folder}: has associations.txt but no rgb.txt or depth.txt; write them from it (for TUM's "
                "'rgb_time rgb_file depth_time depth_file' lines: awk '!/^#/{print $1, $2}' associations.txt > rgb.txt; "
                "awk '!/^#/{print $3, $4}' associations.txt > depth.txt)"
            )
        images = find_image_folders(folder)
        if images is not None and not images.rgb_names:
            raise SequenceFormatError(
                f"{folder}: has {images.colour_folder}/ and depth/ folders "
                "but no rgb.txt or depth.txt, and no colour image has a depth image of the same name to pair with "
                "(for example color/000000.jpg and depth/000000.png); rename them, then run 'tambridge index'"
            )
        if images is not None:
            scale = " --depth-scale 1000" if images.camera_from_open3d else ""
            raise SequenceFormatError(
                f"{folder}: has {images.colour_folder}/ and depth/ images but no rgb.txt or depth.txt; "
                f"write them with 'tambridge index {folder} --rate HZ{scale}' (HZ: your camera's frames per second"
                + (", 1000: depth units per metre" if scale else "") + ")"
            )
        raise SequenceFormatError(
            f"{folder}: not a sequence folder (no rgb.txt or depth.txt); "
            "download one with 'tambridge download fr1/desk --to DIR' or make one with 'tambridge synth DIR'"
        )


def open_sequence(
    folder: Path,
    camera_file: Path | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    check_depth_scale: bool = True,
) -> RgbdSequence:
    """Open a TUM-layout folder: associate colour and depth, pick the camera, load ground truth if present.

    ``stride`` keeps every n-th associated frame, ``max_frames`` caps the count after striding.
    Every frame's images are checked before any is decoded (present, not truncated, PNG checksums, headers); the depth
    scale on the first frames that have depth (:func:`check_depth_scale_plausible`), and the first frame's sizes
    against the camera (:func:`check_first_frame`).
    """
    folder = Path(folder)
    check_sequence_folder(folder)
    if stride < 1:
        raise SequenceFormatError(f"stride must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise SequenceFormatError(f"max_frames must be >= 1 (or unset for every frame), got {max_frames}")
    rgb_list = read_file_list(folder / "rgb.txt")
    depth_list = read_file_list(folder / "depth.txt")
    rgb_stamps = np.array([stamp for stamp, _ in rgb_list])
    depth_stamps = np.array([stamp for stamp, _ in depth_list])
    check_stamps_in_seconds(rgb_stamps, folder / "rgb.txt")
    check_stamps_in_seconds(depth_stamps, folder / "depth.txt")
    pairs = associate(rgb_stamps, depth_stamps)
    if not pairs:
        raise SequenceFormatError(
            f"{folder / 'rgb.txt'}: no colour timestamp lies within {MAX_ASSOCIATION_DIFFERENCE_S} s of a depth "
            f"timestamp in depth.txt (rgb {rgb_stamps[0]:.3f}..{rgb_stamps[-1]:.3f}, "
            f"depth {depth_stamps[0]:.3f}..{depth_stamps[-1]:.3f}); check that both lists come from the same recording"
        )
    without_depth = len(rgb_list) - len(pairs)
    pairs = pairs[::stride]
    if max_frames is not None:
        pairs = pairs[:max_frames]
    sensor = find_sensor(folder, camera_file)
    ground_truth = None
    if (folder / "groundtruth.txt").is_file():
        ground_truth = read_tum_trajectory(folder / "groundtruth.txt")
    sequence = RgbdSequence(
        folder=folder,
        sensor=sensor,
        rgb_paths=[folder / rgb_list[i][1] for i, _ in pairs],
        depth_paths=[folder / depth_list[j][1] for _, j in pairs],
        timestamps_s=np.array([rgb_stamps[i] for i, _ in pairs]),
        ground_truth=ground_truth,
        gt_rgb_paths=_gt_rgb_paths(folder, [rgb_list[i][1] for i, _ in pairs]),
        depth_timestamps_s=np.array([depth_stamps[j] for _, j in pairs]),
        colour_images_without_depth=without_depth,
        colour_images_listed=len(rgb_list),
    )
    for rgb_path, depth_path in zip(sequence.rgb_paths, sequence.depth_paths):
        check_image_file(rgb_path, "rgb.txt")
        check_image_file(depth_path, "depth.txt")
    sequence.check_frame_headers()
    for path in (*sequence.rgb_paths, *sequence.depth_paths):
        check_png_checksums(path)
    if check_depth_scale:
        check_depth_scale_plausible(sequence)
    check_first_frame(sequence)
    return sequence


MAX_FRAME_INTERVAL_S = 10.0
"""Median time between an index file's frames above which its stamps are taken for another unit than seconds."""
STAMP_UNITS = (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9))
"""The units a recorder's stamps may be in, with their count per second."""
TYPICAL_FRAME_INTERVAL_S = 1.0 / 30.0
"""An RGB-D camera's usual frame interval: stamps in another unit are read in the one that brings them nearest it."""


def check_stamps_in_seconds(stamps: np.ndarray, path: Path) -> None:
    """Raise :class:`SequenceFormatError` naming ``path`` where its frames lie :data:`MAX_FRAME_INTERVAL_S` or more
    apart (median): TUM's stamps are seconds, and a recorder's milli- to nanoseconds would pass for a camera a day
    apart, failing later as stamps that match nothing, or with frame intervals of years. The unit the message names
    is the one whose interval lies nearest :data:`TYPICAL_FRAME_INTERVAL_S` by ratio (5e6 apart: a 200 Hz camera's
    nanoseconds, not a 0.2 Hz camera's microseconds)."""
    if len(stamps) < 2:
        return
    interval = float(np.median(np.diff(np.sort(stamps))))
    if interval < MAX_FRAME_INTERVAL_S:
        return
    unit, per_second = min(STAMP_UNITS, key=lambda unit: abs(np.log(interval / unit[1] / TYPICAL_FRAME_INTERVAL_S)))
    raise SequenceFormatError(f"{path}: its frames lie {interval:.6g} apart (median); timestamps must be in "
                              f"seconds, and these look like {unit}: divide them by {per_second:g}")


def check_first_frame(sequence: RgbdSequence) -> None:
    """Read frame 0 whole (colour, depth, the colour's registration): a camera file whose size is not the images'
    fails here, naming the image and the key to fix, before a run writes anything rather than at its first frame."""
    sequence[0]


ACCELEROMETER_FILE = "accelerometer.txt"


KINECT_CAMERA_FROM_ACCELEROMETER = np.diag([-1.0, -1.0, 1.0])
"""The Kinect's accelerometer axes in our (OpenCV) camera axes: its x points to the camera's left, y up, z forward.
Its reading is the specific force: at rest it points up, about 9.8 m/s^2 (checked against TUM's motion capture,
docs/export.md)."""


@dataclasses.dataclass
class AccelerometerSamples:
    """TUM's ``accelerometer.txt``: ``timestamps_s`` (N,) increasing and ``acceleration_mps2`` (N, 3) m/s^2, in the
    sensor's own axes (:data:`KINECT_CAMERA_FROM_ACCELEROMETER`)."""

    timestamps_s: np.ndarray
    acceleration_mps2: np.ndarray


def read_accelerometer(path: Path) -> AccelerometerSamples:
    """Parse ``timestamp ax ay az`` lines (``#`` comments); errors name the file and line."""
    rows = []
    for number, line in enumerate(read_text_file(path, SequenceFormatError).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            values = [float(part) for part in parts]
        except ValueError:
            values = []
        if len(values) != 4 or not np.all(np.isfinite(values)):
            raise SequenceFormatError(f"{path} line {number}: expected 4 numbers 'timestamp ax ay az', got {line!r}; "
                                      f"fix the line or remove {path.name} (up then comes from the map's planes)")
        rows.append(values)
    if not rows:
        raise SequenceFormatError(f"{path}: no samples; remove the file (up then comes from the map's planes)")
    rows = np.array(rows)
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    return AccelerometerSamples(rows[:, 0], rows[:, 1:4])


def find_accelerometer(folder: Path) -> AccelerometerSamples | None:
    """The samples of ``folder/accelerometer.txt``, or None where the sequence has none."""
    path = Path(folder) / ACCELEROMETER_FILE
    return read_accelerometer(path) if path.exists() else None
def _gt_rgb_paths(folder: Path, rgb_names: list[str]) -> list[Path] | None:
    """``gt_rgb/`` images named as the frames' colour images, or None without that folder; a missing one fails."""
    if not (folder / GT_RGB_FOLDER).is_dir():
        return None
    paths = [folder / GT_RGB_FOLDER / Path(name).name for name in rgb_names]
    missing = [path for path in paths if not path.is_file()]
    if missing:
        raise SequenceFormatError(f"{missing[0]}: {len(missing)} frames have no sharp image in {GT_RGB_FOLDER}/; "
                                  f"restore them or remove {folder / GT_RGB_FOLDER}")
    return paths


DEPTH_CHECK_FRAMES = 30
"""Frames (the first ones, then spread over the sequence) searched for one with enough depth to check its scale."""
DEPTH_CHECK_MIN_VALID = 0.01
"""Share of valid depth pixels a frame needs for its median to say something about the depth scale."""


def check_depth_scale_plausible(sequence: RgbdSequence) -> None:
    """Raise unless the median valid depth of the first checked frame with enough depth lies in 0.1-10 m (else the
    ``depth_scale`` is wrong), or when none of the checked frames has any depth (nothing could be reconstructed).

    The first ``DEPTH_CHECK_FRAMES // 2`` frames are checked in order, then frames spread over the rest: a
    sequence whose first frames are blank still gets its scale checked."""
    count = len(sequence)
    first = list(range(min(count, DEPTH_CHECK_FRAMES // 2)))
    spread = np.linspace(len(first), count - 1, DEPTH_CHECK_FRAMES - len(first)).astype(int) if count > len(first) else []
    candidates = list(dict.fromkeys([*first, *(int(i) for i in spread)]))
    for index in candidates:
        path = sequence.depth_paths[index]
        depth_m = sequence.read_depth_m(path)
        valid = depth_m[depth_m > 0]
        if valid.size < DEPTH_CHECK_MIN_VALID * depth_m.size:
            continue
        scale = sequence.sensor.depth_scale
        largest_m = np.float32(np.iinfo(np.uint16).max) / np.float32(scale)
        share = float(np.mean(depth_m == largest_m))
        if sequence.sensor.depth_invalid is None and share >= MAX_SATURATED_SHARE:
            # Sensors that mark "no depth" with the largest value (7-Scenes, some drivers) would put those pixels
            # tens of metres away as map geometry.
            raise SequenceFormatError(
                f"{path}: {share:.0%} of its pixels are 65535, the largest 16-bit value ({largest_m:.3g} m at "
                f"depth_scale {scale:g}); if it marks pixels without depth, set depth_invalid: 65535 in camera.yaml "
                "(--camera)"
            )
        median_m = float(np.median(valid))
        low, high = PLAUSIBLE_MEDIAN_DEPTH_M
        if not low <= median_m <= high:
            raw_median = median_m * sequence.sensor.depth_scale
            suggestion = raw_median / 2.0
            raise SequenceFormatError(
                f"{path}: median depth is {median_m:.3g} m with depth_scale {sequence.sensor.depth_scale:g}, outside "
                f"{low}-{high} m; set depth_scale in camera.yaml (--camera) to the raw units per metre "
                f"(TUM 5000, millimetres 1000; about {suggestion:.0f} would put the median at 2 m)"
            )
        return
    raise SequenceFormatError(
        f"{sequence.folder / 'depth.txt'}: none of {len(candidates)} depth images checked (the first and some spread "
        f"over the sequence) has valid depth (at least {DEPTH_CHECK_MIN_VALID:.0%} of pixels above 0); check the depth "
        "images and depth_invalid in camera.yaml"
    )
