"""semloc calibrate-camera SOURCE -o camera.yml: calibrate a camera from views of a chessboard (docs/camera.md).

SOURCE is anything the camera worker reads (a video, an image folder, a device index, a URL, a bag...). Every
``--every``-th frame is searched for the whole board (``--board`` inner corners, ``--square`` metres); once
``--views`` views are found (or the source ends) OpenCV fits a pinhole (plumb_bob distortion) or fisheye
(equidistant) model, and the calibration file the camera worker reads (``calibration:``) is written with its
reprojection error, e.g.

  semloc calibrate-camera board.mp4 -o deploy/local/camera.yml --board 9x6 --square 0.025
  semloc calibrate-camera 0 -o camera.yml --model fisheye      # a live device: move the board around
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from services.commands import fail, logger, print_json

DEFAULT_VIEWS = 40


def board_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d+)[xX](\d+)", text.strip())
    if not match:
        raise argparse.ArgumentTypeError(f"expected COLUMNSxROWS inner corners, e.g. 9x6, got {text!r}")
    return int(match.group(1)), int(match.group(2))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", help="video, image folder, device index, URL, bag... (as the camera worker's)")
    parser.add_argument("-o", "--output", required=True, help="calibration YAML to write (the camera worker's "
                                                              "calibration: file)")
    parser.add_argument("--board", type=board_size, default=(9, 6), metavar="COLSxROWS",
                        help="the chessboard's inner corners (default 9x6)")
    parser.add_argument("--square", type=float, default=0.025, metavar="M", help="square size in metres "
                                                                                  "(default 0.025)")
    parser.add_argument("--model", choices=("pinhole", "fisheye"), default="pinhole",
                        help="pinhole with OpenCV's 5 distortion coefficients (default), or fisheye (equidistant)")
    parser.add_argument("--every", type=int, default=1, metavar="N", help="search every N-th frame (default 1)")
    parser.add_argument("--views", type=int, default=DEFAULT_VIEWS, metavar="N",
                        help=f"stop reading after N views of the board (default {DEFAULT_VIEWS})")
    parser.add_argument("--source-type", default="auto", help="as the camera worker's source_type (default auto)")
    parser.add_argument("--name", default="front", help="camera_name in the file (default front)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def run(args: argparse.Namespace) -> int:
    import itertools

    import yaml

    from semloc_core.camera_calibration import Chessboard, calibrate, find_corners
    from semloc_core.io.errors import FileFormatError
    from semloc_core.io.camera_model import camera_to_mapping
    from services.camera_sources import SourceError, open_source

    say = logger(args.quiet)
    try:
        board = Chessboard(*args.board, square_m=args.square)
        if args.every < 1 or args.views < 1:
            raise ValueError("--every and --views must be at least 1")
        source = open_source(args.source, args.source_type)
        source.on_skip = lambda _why, detail: say(detail)  # an unreadable frame is one view fewer, no more
    except (ValueError, FileFormatError) as error:
        return fail("calibrate-camera", error)
    corners, size, frames = [], None, 0
    try:
        for capture in itertools.islice(source, 0, None, args.every):
            frames += 1
            image = capture.images[0]
            if size is None:
                size = (image.shape[1], image.shape[0])
            elif (image.shape[1], image.shape[0]) != size:
                raise ValueError(f"frame {frames * args.every - args.every} is {image.shape[1]}x{image.shape[0]}, "
                                 f"the first {size[0]}x{size[1]}")
            found = find_corners(image, board)
            if found is not None:
                corners.append(found)
            say(f"frame {frames * args.every - args.every}: {'board' if found is not None else 'no board'} "
                f"({len(corners)}/{args.views} views)")
            if len(corners) >= args.views:
                break
        if size is None:
            raise ValueError(f"no frame in {args.source}")
        result = calibrate(corners, board, *size, model=args.model)
    except (ValueError, SourceError) as error:  # SourceError: a live source that stopped
        return fail("calibrate-camera", error)
    finally:
        source.close()
    document = camera_to_mapping(result.camera, args.name)
    document["reprojection_error_px"] = round(result.rms_px, 4)
    document["views"] = result.views
    output = Path(args.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(yaml.safe_dump(document, sort_keys=False))
    K = result.camera.K
    summary = {"output": str(output), "model": args.model, "width": size[0], "height": size[1], "views": result.views,
               "frames_read": frames, "reprojection_error_px": result.rms_px,
               "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "dist": result.camera.dist.tolist()}
    if args.json:
        print_json(summary)
    else:
        print(f"{args.model} {size[0]}x{size[1]} from {result.views} views: fx={K[0, 0]:.2f} fy={K[1, 1]:.2f} "
              f"cx={K[0, 2]:.2f} cy={K[1, 2]:.2f}, reprojection error {result.rms_px:.3f} px RMS; wrote {output}")
    return 0
