"""A TUM-layout copy of a sequence with the camera sped up and blurred: every ``--stride``-th colour frame of
rgb.txt, each the mean of the ``--exposure-frames`` (odd) recorded colour frames centred on it (a longer exposure,
blurred along the camera's real motion), written under the original names (encoded by their extension) and stamps;
depth, depth.txt, groundtruth.txt, accelerometer.txt and the camera file are linked as they are (the reader
associates depth with the kept colour stamps). For whole runs of ``tambridge reconstruct`` on faster motion than a
recording has, with its own ground truth:

    python benchmarks/sped_up_sequence.py DATA/rgbd_dataset_freiburg1_xyz OUT/rgbd_dataset_freiburg1_xyz_stride6_blur3 --stride 6
    tambridge reconstruct OUT/rgbd_dataset_freiburg1_xyz_stride6_blur3 -o OUT/run

The raw images are averaged, before the reader's undistortion, so the folder keeps the source's camera (name it
with ``freiburg1`` for the TUM fr1 calibration, as above). ``benchmarks/dense_tracking.py --strides N
--exposure-frames M`` makes similar frames in memory for tracking alone (from the frames the reader pairs with
depth, starting at the first).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tambridge.errors import TambridgeError  # noqa: E402
from tambridge.files import check_new_or_empty_folder  # noqa: E402
from tambridge.io.tum import check_image_file, read_file_list  # noqa: E402

LINKED = ("depth", "depth.txt", "groundtruth.txt", "accelerometer.txt", "camera.yaml", "camera.yml", "camera.txt")
"""What the copy takes from the source as it is: the depth, the lists and files the reader and export look for."""


def mean_exposure(images: list[np.ndarray]) -> np.ndarray:
    """The mean of same-sized 8-bit images, rounded back to uint8: one frame of a longer exposure."""
    return np.clip(np.rint(np.mean(np.stack(images).astype(np.float32), axis=0)), 0, 255).astype(np.uint8)


def write_sped_up(source: Path, folder: Path, stride: int, exposure_frames: int) -> int:
    """Write the copy into ``folder`` (which must exist); returns the number of colour frames kept. Frames are kept
    from the first whose whole exposure window lies in the recording (rgb.txt row ``exposure_frames // 2``) on.
    Every colour image is checked before anything is written (:class:`TambridgeError` naming the file)."""
    colour = read_file_list(source / "rgb.txt")
    half = exposure_frames // 2
    kept = list(range(half, len(colour) - half, stride))
    if not kept:
        raise TambridgeError(f"{source / 'rgb.txt'}: lists {len(colour)} colour frames, fewer than one exposure of "
                             f"{exposure_frames}; give a longer sequence or fewer --exposure-frames")
    for _, name in colour:
        check_image_file(source / name, "rgb.txt")
    for index in kept:
        # Decoded as the reader decodes colour (8-bit, three channels), whatever the file holds.
        window = [cv2.imread(str(source / colour[j][1]), cv2.IMREAD_COLOR) for j in range(index - half, index + half + 1)]
        if any(image is None for image in window):
            raise TambridgeError(f"{source}: a colour image around {colour[index][1]} cannot be decoded; re-extract the sequence")
        target = folder / colour[index][1]
        target.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(target), mean_exposure(window))
    (folder / "rgb.txt").write_text("".join(f"{colour[i][0]:.6f} {colour[i][1]}\n" for i in kept))
    for name in LINKED:
        if (source / name).exists():
            (folder / name).symlink_to((source / name).resolve())
    return len(kept)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path, help="a TUM-layout sequence folder")
    parser.add_argument("folder", type=Path, help="the copy to write (new or empty)")
    parser.add_argument("--stride", type=int, default=6, help="keep every n-th colour frame (default 6)")
    parser.add_argument("--exposure-frames", type=int, default=3, help="recorded frames averaged into each (odd; default 3)")
    args = parser.parse_args()
    if args.stride < 1:
        parser.error(f"--stride {args.stride}: must be 1 or more")
    if args.exposure_frames < 1 or args.exposure_frames % 2 == 0:
        parser.error(f"--exposure-frames {args.exposure_frames}: give an odd count, 1 or more")
    if not (args.source / "rgb.txt").is_file():
        parser.error(f"{args.source}: has no rgb.txt; give a TUM-layout sequence folder")
    try:
        check_new_or_empty_folder(args.folder)
        args.folder.mkdir(parents=True, exist_ok=True)
        print(f"wrote {write_sped_up(args.source, args.folder, args.stride, args.exposure_frames)} frames to {args.folder}")
    except TambridgeError as error:
        raise SystemExit(f"error: {error}") from None


if __name__ == "__main__":
    main()
